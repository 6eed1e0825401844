"""The solver's LAPACK calls equal SciPy's functions bit for bit, without ``scipy.linalg``.

:mod:`vhm_viz.core.lapack` loads SciPy's compiled LAPACK wrappers without running the
``scipy.linalg`` package's ``__init__``; its QR and triangular solves must give exactly
what :func:`scipy.linalg.qr` and :func:`scipy.linalg.solve_triangular` give.
"""

import subprocess
import sys

import numpy as np
import pytest
import scipy.linalg as sla
from conftest import subprocess_env

from vhm_viz.core import lapack

RNG = np.random.default_rng(34)


def _matrices():
    tall = RNG.standard_normal((40, 12))
    wide = RNG.standard_normal((7, 19))
    deficient = tall[:, :6] @ RNG.standard_normal((6, 12))  # rank 6 of 12 columns
    return {"tall": tall, "tall_fortran": np.asfortranarray(tall), "tall_T": wide.T,
            "wide": wide, "rank_deficient": deficient}  # fmt: skip


@pytest.mark.parametrize("name", list(_matrices()))
@pytest.mark.parametrize(("economic", "pivoting"), [(True, False), (False, True), (False, False)])
def test_qr_is_scipys_bit_for_bit(name, economic, pivoting):
    a = _matrices()[name]
    mode = "economic" if economic else "full"
    expected = sla.qr(a.copy(order="K"), mode=mode, pivoting=pivoting, check_finite=False)
    got = lapack.qr(a.copy(order="K"), economic=economic, pivoting=pivoting)
    assert len(got) == len(expected)
    for g, e in zip(got, expected, strict=True):
        assert g.shape == e.shape and g.dtype == e.dtype
        assert np.array_equal(g, e)
    q, r = got[0], got[1]
    cols = got[2] if pivoting else np.arange(a.shape[1])
    assert np.allclose(q @ r, a[:, cols], atol=1e-12)


def test_qr_overwrites_a_fortran_input_only_when_allowed():
    a = np.asfortranarray(RNG.standard_normal((30, 8)))
    kept = a.copy()
    q, r = lapack.qr(a, economic=True)
    assert np.array_equal(a, kept)
    q2, r2 = lapack.qr(a, economic=True, overwrite_a=True)
    assert np.array_equal(q2, q) and np.array_equal(r2, r)
    assert not np.array_equal(a, kept)  # the packed factors or Q went into a


@pytest.mark.parametrize("transpose", [False, True])
@pytest.mark.parametrize("order", ["C", "F"])
@pytest.mark.parametrize("rhs", [(9,), (9, 4)])
def test_solve_triangular_is_scipys_bit_for_bit(transpose, order, rhs):
    a = np.triu(RNG.standard_normal((9, 9))) + 4 * np.eye(9)
    a = np.asarray(a, order=order)
    b = RNG.standard_normal(rhs)
    trans = "T" if transpose else "N"
    expected = sla.solve_triangular(a, b, trans=trans, check_finite=False)
    got = lapack.solve_triangular(a, b, transpose=transpose)
    assert np.array_equal(got, expected)
    assert np.allclose((a.T if transpose else a) @ got, b)


def test_a_singular_triangle_is_refused():
    a = np.triu(np.ones((4, 4)))
    a[2, 2] = 0.0
    with pytest.raises(np.linalg.LinAlgError, match="diagonal 2"):
        lapack.solve_triangular(a, np.ones(4))


def test_scipy_linalg_imported_afterwards_works_beside_it():
    """Loaded first, the extensions do not spoil a later ``import scipy.linalg``: its
    functions, its Cython modules (which import the ones loaded here) and ours agree."""
    code = (
        "import numpy as np\n"
        "from vhm_viz.core import lapack\n"
        "lapack.register_cython_linalg()\n"
        "a = np.random.default_rng(1).standard_normal((9, 5))\n"
        "ours = lapack.qr(a, pivoting=True)\n"
        "import scipy.linalg as sla\n"
        "import scipy.linalg.cython_lapack\n"
        "theirs = sla.qr(a, pivoting=True, check_finite=False)\n"
        "assert all(np.array_equal(x, y) for x, y in zip(ours, theirs))\n"
        "q, r = sla.qr_update(*sla.qr(a)[:2], np.ones(9), np.ones(5))\n"
        "assert np.allclose(q @ r, a + np.outer(np.ones(9), np.ones(5)))\n"
        "print('ok')\n"
    )
    _prints_ok(code)


def test_kd_tree_without_scipy_spatial_is_scipys_and_stays_so():
    """The KD-tree loaded without ``scipy.spatial``'s ``__init__`` (which the command line
    never imports for it) answers as ``scipy.spatial.cKDTree`` does, and is its class once
    ``scipy.spatial`` is imported afterwards."""
    code = (
        "import sys\n"
        "import numpy as np\n"
        "from vhm_viz.core.scipy_extensions import kd_tree\n"
        "rng = np.random.default_rng(2)\n"
        "points, queries = rng.random((500, 3)), rng.random((50, 3))\n"
        "tree = kd_tree(points, leafsize=8)\n"
        "ours = tree.query(queries, k=3)\n"
        "assert 'scipy.spatial' not in sys.modules, 'scipy.spatial was imported'\n"
        "import scipy.spatial\n"
        "assert isinstance(tree, scipy.spatial.cKDTree)\n"
        "theirs = scipy.spatial.cKDTree(points, leafsize=8).query(queries, k=3)\n"
        "assert all(np.array_equal(x, y) for x, y in zip(ours, theirs))\n"
        "assert sorted(tree.query_ball_point(queries[0], 0.2)) == sorted(\n"
        "    scipy.spatial.KDTree(points).query_ball_point(queries[0], 0.2))\n"
        "print('ok')\n"
    )
    _prints_ok(code)


def _prints_ok(code: str) -> None:
    """Run ``code`` in a fresh interpreter: it must print ``ok`` and exit 0."""
    res = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=subprocess_env()
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "ok"
