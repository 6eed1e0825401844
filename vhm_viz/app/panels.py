"""Side panels of the explorer: constraints, solver settings and the analysis dock.

The constraint list allows numeric editing; the analysis dock has the measure choice, a
histogram, the energy plot and the metrics.

The plots are drawn with ``QPainter`` (no plotting library needed).
"""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import QPointF, QRectF, Qt, Signal
from PySide6.QtGui import QColor, QPainter, QPen
from PySide6.QtWidgets import (
    QAbstractItemView,
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFormLayout,
    QGroupBox,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QPushButton,
    QSlider,
    QSpinBox,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from vhm_viz.colours import MEASURES

__all__ = [
    "ConstraintPanel",
    "AnalysisPanel",
    "ViewPanel",
    "PlotWidget",
    "alpha_from_slider",
    "slider_from_alpha",
]

# alpha slider: log scale 1e-4 .. 1e-1 in 60 steps
_ALPHA_LO, _ALPHA_HI, _ALPHA_STEPS = -4.0, -1.0, 60


def alpha_from_slider(v: int) -> float:
    """Slider position (0..60) -> alpha on a log scale from 1e-4 to 1e-1."""
    return float(10 ** (_ALPHA_LO + (_ALPHA_HI - _ALPHA_LO) * v / _ALPHA_STEPS))


def slider_from_alpha(alpha: float) -> int:
    """Inverse of :func:`alpha_from_slider` (rounded, clamped)."""
    t = (np.log10(alpha) - _ALPHA_LO) / (_ALPHA_HI - _ALPHA_LO)
    return int(np.clip(round(t * _ALPHA_STEPS), 0, _ALPHA_STEPS))


class ConstraintPanel(QWidget):
    """Solver settings and the constraint table.

    Rows are ``P i`` (position: target x, y, z editable) and ``J i`` (Jacobian: angles
    about x, y, z in degrees and scale editable).

    Signals
    -------
    target_edited(int, object)
        Position constraint index, new (3,) target.
    jacobian_edited(int, object, float)
        Jacobian constraint index, (3,) angles in degrees, scale.
    delete_requested(str, int)
        ``"position"``/``"jacobian"`` and index.
    mode_changed(str), alpha_changed(float)
    """

    target_edited = Signal(int, object)
    jacobian_edited = Signal(int, object, float)
    delete_requested = Signal(str, int)
    mode_changed = Signal(str)
    alpha_changed = Signal(float)

    HEADERS = ("", "x / ax", "y / ay", "z / az", "scale")

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QVBoxLayout(self)
        box = QGroupBox("Solver")
        form = QFormLayout(box)
        self.mode = QComboBox()
        self.mode.addItems(["rigid", "similar"])
        self.mode.currentTextChanged.connect(self.mode_changed)
        form.addRow("Mode", self.mode)
        row = QHBoxLayout()
        self.alpha = QSlider(Qt.Orientation.Horizontal)
        self.alpha.setRange(0, _ALPHA_STEPS)
        self.alpha.setValue(slider_from_alpha(0.01))
        self.alpha_label = QLabel("0.01")
        self.alpha.valueChanged.connect(self._alpha_moved)
        self.alpha.sliderReleased.connect(lambda: self.alpha_changed.emit(self.alpha_value))
        row.addWidget(self.alpha)
        row.addWidget(self.alpha_label)
        form.addRow("alpha", row)
        self.iterations = QSpinBox()
        self.iterations.setRange(1, 100000)
        self.iterations.setValue(200)
        form.addRow("Max iterations", self.iterations)
        lay.addWidget(box)

        lay.addWidget(QLabel("Constraints (edit cells; rest point in tooltip)"))
        self.table = QTableWidget(0, len(self.HEADERS))
        self.table.setHorizontalHeaderLabels(self.HEADERS)
        self.table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.Stretch)
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.itemChanged.connect(self._item_changed)
        lay.addWidget(self.table)
        self.delete = QPushButton("Delete selected")
        self.delete.clicked.connect(self._delete_selected)
        lay.addWidget(self.delete)
        self._rows: list[tuple[str, int]] = []
        self._filling = False

    @property
    def alpha_value(self) -> float:
        """Alpha of the slider position."""
        return alpha_from_slider(self.alpha.value())

    def _alpha_moved(self, v: int) -> None:
        self.alpha_label.setText(f"{alpha_from_slider(v):.3g}")
        if not self.alpha.isSliderDown():  # keyboard / programmatic change
            self.alpha_changed.emit(alpha_from_slider(v))

    def set_alpha(self, alpha: float) -> None:
        """Show ``alpha`` without emitting signals."""
        self.alpha.blockSignals(True)
        self.alpha.setValue(slider_from_alpha(alpha))
        self.alpha.blockSignals(False)
        self.alpha_label.setText(f"{alpha:.3g}")

    def set_mode(self, mode: str) -> None:
        """Show ``mode`` without emitting signals."""
        self.mode.blockSignals(True)
        self.mode.setCurrentText(mode)
        self.mode.blockSignals(False)

    def fill(self, positions, jacobians) -> None:
        """Show the controller's constraints."""
        self._filling = True
        try:
            self.table.setRowCount(len(positions) + len(jacobians))
            self._rows = []
            r = 0
            for i, c in enumerate(positions):
                self._set_row(r, f"P {i}", [*c.target, None], c.point)
                self._rows.append(("position", i))
                r += 1
            for i, c in enumerate(jacobians):
                self._set_row(r, f"J {i}", [*c.angles, c.scale], c.point)
                self._rows.append(("jacobian", i))
                r += 1
        finally:
            self._filling = False

    def _set_row(self, r: int, label: str, values, point) -> None:
        head = QTableWidgetItem(label)
        head.setFlags(Qt.ItemFlag.ItemIsSelectable | Qt.ItemFlag.ItemIsEnabled)
        tip = "rest point " + ", ".join(f"{v:.4g}" for v in point)
        head.setToolTip(tip)
        self.table.setItem(r, 0, head)
        for k, v in enumerate(values):
            it = QTableWidgetItem("" if v is None else f"{v:.6g}")
            if v is None:
                it.setFlags(Qt.ItemFlag.ItemIsEnabled)
            it.setToolTip(tip)
            self.table.setItem(r, k + 1, it)

    def _row_values(self, r: int) -> list[float]:
        vals = []
        for k in range(1, len(self.HEADERS)):
            it = self.table.item(r, k)
            text = it.text() if it is not None else ""
            vals.append(float(text) if text.strip() else float("nan"))
        return vals

    def _item_changed(self, item: QTableWidgetItem) -> None:
        if self._filling or item.column() == 0:
            return
        r = item.row()
        if r >= len(self._rows):
            return
        kind, i = self._rows[r]
        try:
            vals = self._row_values(r)
        except ValueError:
            item.setText("")  # not a number; the window re-fills from the controller
            self.target_edited.emit(-1, None)
            return
        if kind == "position":
            self.target_edited.emit(i, np.array(vals[:3]))
        else:
            self.jacobian_edited.emit(i, np.array(vals[:3]), vals[3])

    def selected_rows(self) -> list[tuple[str, int]]:
        """(kind, index) of the selected constraints, last row first."""
        rows = sorted({ix.row() for ix in self.table.selectedIndexes()}, reverse=True)
        return [self._rows[r] for r in rows if r < len(self._rows)]

    def _delete_selected(self) -> None:
        for row in self.selected_rows():
            self.delete_requested.emit(*row)


class PlotWidget(QWidget):
    """Minimal line / bar plot drawn with QPainter."""

    def __init__(self, title: str, parent=None):
        super().__init__(parent)
        self.title = title
        self.setMinimumHeight(120)
        self._bars = None  # (edges, counts)
        self._lines: list[tuple[np.ndarray, np.ndarray, QColor]] = []
        self._logy = False
        self._log = False
        self._marker = None

    def set_histogram(self, hist, marker: float | None = None, log: bool = False) -> None:
        """Draw a :class:`vhm_viz.colours.Histogram` (every value counted).

        Values under and over the drawn range, and non-finite ones, are drawn as labelled
        end bins with their counts; ``marker`` draws a vertical line (e.g. det J = 1);
        ``log``: the bins are equal in log (det J).
        """
        self._lines = []
        self._marker = marker
        self._log = bool(log)
        self._bars = None if hist is None or hist.total == 0 else hist
        self.update()

    def end_labels(self) -> list[str]:
        """Texts of the underflow / overflow / non-finite bins that hold values."""
        h = self._bars
        if h is None:
            return []
        lo, hi = h.edges[0], h.edges[-1]
        out = []
        if h.below:
            out.append(f"< {lo:.3g}: {h.below}")
        if h.above:
            out.append(f"> {hi:.3g}: {h.above}")
        if h.nonfinite:
            out.append(f"non-finite: {h.nonfinite}")
        return out

    def set_lines(self, ys: list[np.ndarray], logy: bool = True) -> None:
        """Plot curves against their index (energy vs iteration)."""
        colors = [QColor(30, 90, 200), QColor(200, 60, 40), QColor(40, 150, 60)]
        self._bars = None
        self._logy = logy
        self._lines = [
            (np.arange(len(y), dtype=float), np.asarray(y, float), colors[k % 3])
            for k, y in enumerate(ys)
            if len(y)
        ]
        self.update()

    def paintEvent(self, event) -> None:  # noqa: N802, D102 - Qt override
        p = QPainter(self)
        p.fillRect(self.rect(), QColor(255, 255, 255))
        m = 24
        area = QRectF(m + 10, m, self.width() - 2 * m - 10, self.height() - 2 * m)
        p.setPen(QColor(0, 0, 0))
        p.drawText(QPointF(m, 14), self.title)
        p.drawRect(area)
        if self._bars is not None:
            h = self._bars
            edges, counts = h.edges, h.counts
            pos = np.log(edges) if self._log else edges
            ends = [c for c in (h.below, h.above) if c]
            cmax = max(int(counts.max()) if counts.size else 0, *ends, 1)
            x0, x1 = pos[0], pos[-1]
            # the underflow / overflow bins: grey bars outside the range, labelled
            gap = 0.06 * area.width()
            inner = QRectF(area.left() + gap, area.top(), area.width() - 2 * gap, area.height())

            def bar(xa, xb, c, colour):
                hgt = c / cmax * inner.height()
                p.setBrush(colour)
                p.drawRect(QRectF(xa, inner.bottom() - hgt, max(xb - xa - 1, 1), hgt))

            for k, c in enumerate(counts):
                xa = inner.left() + (pos[k] - x0) / (x1 - x0) * inner.width()
                xb = inner.left() + (pos[k + 1] - x0) / (x1 - x0) * inner.width()
                bar(xa, xb, c, QColor(90, 120, 200))
            if h.below:
                bar(area.left() + 2, inner.left() - 2, h.below, QColor(120, 120, 120))
            if h.above:
                bar(inner.right() + 2, area.right() - 2, h.above, QColor(120, 120, 120))
            if self._marker is not None and edges[0] <= self._marker <= edges[-1]:
                m = np.log(self._marker) if self._log else self._marker
                xm = inner.left() + (m - x0) / (x1 - x0) * inner.width()
                p.setPen(QPen(QColor(220, 0, 0), 2))
                p.drawLine(QPointF(xm, area.top()), QPointF(xm, area.bottom()))
            p.setPen(QColor(0, 0, 0))
            p.drawText(QPointF(inner.left(), self.height() - 6), f"{edges[0]:.3g}")
            p.drawText(QPointF(inner.right() - 40, self.height() - 6), f"{edges[-1]:.3g}")
            p.drawText(QPointF(2, area.top() + 10), str(cmax))
            labels = self.end_labels()
            if labels:
                p.drawText(QPointF(area.left() + 4, area.top() + 14), "   ".join(labels))
        elif self._lines:
            ys = np.concatenate([y for _, y, _ in self._lines])
            if self._logy:
                ys = np.log10(np.maximum(ys, 1e-300))
            ylo, yhi = float(ys.min()), float(ys.max())
            if yhi <= ylo:
                ylo, yhi = ylo - 1, yhi + 1
            xmax = max(max(len(x) for x, _, _ in self._lines) - 1, 1)
            for x, y, col in self._lines:
                yy = np.log10(np.maximum(y, 1e-300)) if self._logy else y
                px = area.left() + x / xmax * area.width()
                py = area.bottom() - (yy - ylo) / (yhi - ylo) * area.height()
                p.setPen(QPen(col, 2))
                for k in range(len(px) - 1):
                    p.drawLine(QPointF(px[k], py[k]), QPointF(px[k + 1], py[k + 1]))
            p.setPen(QColor(0, 0, 0))
            lab = "log10 " if self._logy else ""
            p.drawText(QPointF(2, area.top() + 10), f"{lab}{yhi:.3g}")
            p.drawText(QPointF(2, area.bottom()), f"{ylo:.3g}")
            p.drawText(QPointF(area.right() - 60, self.height() - 6), f"iter {xmax}")
        p.end()


class AnalysisPanel(QWidget):
    """Slice controls, measure histogram, energy plot and metrics.

    Signals
    -------
    slice_toggled(bool), measure_changed(str), live_toggled(bool), clip_toggled(bool)
    """

    slice_toggled = Signal(bool)
    measure_changed = Signal(str)
    live_toggled = Signal(bool)
    clip_toggled = Signal(bool)

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QVBoxLayout(self)
        row = QHBoxLayout()
        self.show_slice = QCheckBox("Slice")
        self.show_slice.toggled.connect(self.slice_toggled)
        self.measure = QComboBox()
        self.measure.addItems(list(MEASURES))
        self.measure.currentTextChanged.connect(self.measure_changed)
        self.live = QCheckBox("Live")
        self.live.setToolTip("Update the slice on every drag frame (else on release)")
        self.live.toggled.connect(self.live_toggled)
        self.clip = QCheckBox("Cut shape")
        self.clip.setChecked(True)
        self.clip.setToolTip("Cut the shape open along the slice plane")
        self.clip.toggled.connect(self.clip_toggled)
        row.addWidget(self.show_slice)
        row.addWidget(self.measure)
        row.addWidget(self.clip)
        row.addWidget(self.live)
        lay.addLayout(row)
        self.resolution = QDoubleSpinBox()
        self.resolution.setDecimals(0)
        self.resolution.setRange(10, 200)
        self.resolution.setValue(60)
        self.resolution.setKeyboardTracking(False)  # typed digits: one resample, on Enter
        form = QFormLayout()
        form.addRow("Slice samples per side", self.resolution)
        lay.addLayout(form)
        self.histogram = PlotWidget("Histogram (slice)")
        self.energy = PlotWidget("Energy vs iteration (total, rigidity, smoothness)")
        lay.addWidget(self.histogram)
        lay.addWidget(self.energy)
        self.metrics = QLabel("-")
        self.metrics.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.metrics.setWordWrap(True)
        lay.addWidget(self.metrics)

    def show_metrics(self, m: dict) -> None:
        """Show E_rigid, E_volume, foldovers, inverted cells, certificate, energy, iterations."""
        parts = []
        for key, fmt in (
            ("E_rigid", "{:.4g}"),
            ("E_volume", "{:.4g}"),
            ("foldovers", "{:d}"),
            ("inverted_cells", "{:d}"),
            ("certificate", "{}"),
            ("energy", "{:.4g}"),
            ("iterations", "{:d}"),
        ):
            if key in m and m[key] is not None:
                v = m[key]
                if isinstance(v, float) and not np.isfinite(v):
                    continue
                parts.append(f"{key}: " + fmt.format(v))
        self.metrics.setText("   ".join(parts) if parts else "-")


def _slider(lo: int, hi: int, value: int) -> QSlider:
    s = QSlider(Qt.Orientation.Horizontal)
    s.setRange(lo, hi)
    s.setValue(value)
    return s


class ViewPanel(QWidget):
    """Opacities of shape and cage; a volume's slices, volume rendering and isosurface.

    The transfer function of the volume rendering is a window/level ramp: opacity 0 below
    ``level - width / 2``, rising linearly to ``opacity`` at ``level + width / 2``; the
    grey ramp of the colours spans the same window (slices use it too).

    Signals
    -------
    shape_opacity_changed(float), cage_opacity_changed(float)
        0..1.
    slices_toggled(bool), slice_moved(int axis, int index), slice_released(int axis)
    slice_colour_changed(str)
        ``"value"``, ``"determinant"`` or ``"condition_number"``.
    volume_toggled(bool), transfer_changed(float level, float width, float opacity)
    iso_changed(bool shown, float value)
    """

    shape_opacity_changed = Signal(float)
    cage_opacity_changed = Signal(float)
    slices_toggled = Signal(bool)
    slice_moved = Signal(int, int)
    slice_released = Signal(int)
    slice_colour_changed = Signal(str)
    volume_toggled = Signal(bool)
    transfer_changed = Signal(float, float, float)
    iso_changed = Signal(bool, float)

    COLOURS = ("value", *MEASURES)
    STEPS = 1000  # slider steps over the value range

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QVBoxLayout(self)
        form = QFormLayout()
        self.shape_opacity = _slider(0, 100, 100)
        self.cage_opacity = _slider(0, 100, 100)
        self.shape_opacity.valueChanged.connect(
            lambda v: self.shape_opacity_changed.emit(v / 100.0)
        )
        self.cage_opacity.valueChanged.connect(lambda v: self.cage_opacity_changed.emit(v / 100.0))
        form.addRow("Shape opacity", self.shape_opacity)
        form.addRow("Cage opacity", self.cage_opacity)
        lay.addLayout(form)
        self.volume_box = QGroupBox("Volume")
        vform = QFormLayout(self.volume_box)
        self.slices = QCheckBox("Slices")
        self.slices.setChecked(True)
        self.slices.toggled.connect(self.slices_toggled)
        self.slice_colour = QComboBox()
        self.slice_colour.addItems(list(self.COLOURS))
        self.slice_colour.currentTextChanged.connect(self.slice_colour_changed)
        row = QHBoxLayout()
        row.addWidget(self.slices)
        row.addWidget(self.slice_colour)
        vform.addRow(row)
        self.slice_sliders = []
        for axis, name in enumerate("xyz"):
            s = _slider(0, 1, 0)
            s.valueChanged.connect(lambda v, a=axis: self.slice_moved.emit(a, int(v)))
            s.sliderReleased.connect(lambda a=axis: self.slice_released.emit(a))
            self.slice_sliders.append(s)
            vform.addRow(f"{name} slice", s)
        self.volume = QCheckBox("Volume rendering")
        self.volume.toggled.connect(self.volume_toggled)
        vform.addRow(self.volume)
        self.level = _slider(0, self.STEPS, self.STEPS // 2)
        self.width = _slider(1, self.STEPS, self.STEPS // 2)
        self.opacity = _slider(0, 100, 30)
        for s in (self.level, self.width, self.opacity):
            s.valueChanged.connect(self._transfer)
        vform.addRow("Level", self.level)
        vform.addRow("Window", self.width)
        vform.addRow("Max opacity", self.opacity)
        self.iso = QCheckBox("Isosurface")
        self.iso_value = _slider(0, self.STEPS, self.STEPS // 2)
        # the contour follows every settled value: keys, the wheel and clicks on the groove
        # at once, a dragged handle on release (no contour per step of the drag)
        self.iso_value.setTracking(False)
        self.iso.toggled.connect(self._iso)
        self.iso_value.valueChanged.connect(self._iso)
        vform.addRow(self.iso, self.iso_value)
        lay.addWidget(self.volume_box)
        lay.addStretch(1)
        self.range = (0.0, 1.0)
        self.volume_box.setEnabled(False)

    def value_of(self, step: int) -> float:
        """Data value of a slider step (over :attr:`range`)."""
        lo, hi = self.range
        return lo + (hi - lo) * step / self.STEPS

    def step_of(self, value: float) -> int:
        """Slider step of a data value (clamped)."""
        lo, hi = self.range
        t = (value - lo) / (hi - lo) if hi > lo else 0.0
        return int(np.clip(round(t * self.STEPS), 0, self.STEPS))

    @property
    def transfer(self) -> tuple[float, float, float]:
        """(level, width, max opacity) of the ramp, in data values."""
        lo, hi = self.range
        return (
            self.value_of(self.level.value()),
            (hi - lo) * self.width.value() / self.STEPS,
            self.opacity.value() / 100.0,
        )

    def set_transfer(self, level: float, width: float, opacity: float) -> None:
        """Move the ramp's sliders (emits :attr:`transfer_changed` once)."""
        lo, hi = self.range
        for s in (self.level, self.width, self.opacity):
            s.blockSignals(True)
        self.level.setValue(self.step_of(level))
        self.width.setValue(max(1, int(round(width / (hi - lo) * self.STEPS))) if hi > lo else 1)
        self.opacity.setValue(int(round(100 * opacity)))
        for s in (self.level, self.width, self.opacity):
            s.blockSignals(False)
        self._transfer()

    def _transfer(self, *args) -> None:
        self.transfer_changed.emit(*self.transfer)

    def _iso(self, *args) -> None:
        self.iso_changed.emit(self.iso.isChecked(), self.value_of(self.iso_value.value()))

    def set_volume(self, dimensions, value_range, index) -> None:
        """Enable the volume controls for a grid (None: disable them)."""
        self.volume_box.setEnabled(dimensions is not None)
        if dimensions is None:
            return
        self.range = tuple(float(v) for v in value_range)
        for s, n, i in zip(self.slice_sliders, dimensions, index, strict=True):
            s.blockSignals(True)
            s.setRange(0, int(n) - 1)
            s.setValue(int(i))
            s.blockSignals(False)
