"""The explorer's undo history without Qt: taking back the record of a failed edit."""

from __future__ import annotations

from vhm_viz.app.explorer_scene import empty_scene
from vhm_viz.app.history import SceneHistory


def test_taking_back_a_record_leaves_the_history_as_it_was_before_it():
    a, b, c, d = (empty_scene(alpha=alpha) for alpha in (1.0, 2.0, 3.0, 4.0))
    history = SceneHistory(limit=2)
    history.record(a)
    history.record(b)
    assert history.undo(c) is b  # a to undo, c to redo
    history.record(d)  # clears the redo history
    assert history.take_back() is d
    assert history.take_back() is None  # one record, taken back once
    assert history.redo(b).alpha == 3.0 and history.undo(c).alpha == 2.0  # redo came back
    assert history.undo(b) is a and not history.can_undo
    # a record beyond the limit forgets the oldest step: taking it back brings it back
    history.record(b)
    history.record(c)
    history.record(d)
    assert history.take_back() is d
    assert history.undo(d) is c and history.undo(c) is b and not history.can_undo
    # after an undo or redo there is nothing to take back
    history.record(a)
    history.undo(b)
    assert history.take_back() is None and history.can_redo
