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

__all__ = [
    "ConstraintPanel",
    "AnalysisPanel",
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

    def _delete_selected(self) -> None:
        rows = sorted({ix.row() for ix in self.table.selectedIndexes()}, reverse=True)
        for r in rows:
            if r < len(self._rows):
                self.delete_requested.emit(*self._rows[r])


class PlotWidget(QWidget):
    """Minimal line / bar plot drawn with QPainter."""

    def __init__(self, title: str, parent=None):
        super().__init__(parent)
        self.title = title
        self.setMinimumHeight(120)
        self._bars = None  # (edges, counts)
        self._lines: list[tuple[np.ndarray, np.ndarray, QColor]] = []
        self._logy = False
        self._marker = None

    def set_histogram(self, values, bins: int = 40, marker: float | None = None) -> None:
        """Histogram of finite ``values``; ``marker`` draws a vertical line (e.g. det = 0)."""
        v = np.asarray(values, dtype=float)
        v = v[np.isfinite(v)]
        self._lines = []
        self._marker = marker
        if v.size == 0:
            self._bars = None
        else:
            lo, hi = float(v.min()), float(v.max())
            if hi <= lo:
                lo, hi = lo - 0.5, hi + 0.5
            counts, edges = np.histogram(v, bins=bins, range=(lo, hi))
            self._bars = (edges, counts)
        self.update()

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
            edges, counts = self._bars
            cmax = max(int(counts.max()), 1)
            x0, x1 = edges[0], edges[-1]
            p.setBrush(QColor(90, 120, 200))
            for k, c in enumerate(counts):
                xa = area.left() + (edges[k] - x0) / (x1 - x0) * area.width()
                xb = area.left() + (edges[k + 1] - x0) / (x1 - x0) * area.width()
                h = c / cmax * area.height()
                p.drawRect(QRectF(xa, area.bottom() - h, max(xb - xa - 1, 1), h))
            if self._marker is not None and x0 <= self._marker <= x1:
                xm = area.left() + (self._marker - x0) / (x1 - x0) * area.width()
                p.setPen(QPen(QColor(220, 0, 0), 2))
                p.drawLine(QPointF(xm, area.top()), QPointF(xm, area.bottom()))
            p.setPen(QColor(0, 0, 0))
            p.drawText(QPointF(area.left(), self.height() - 6), f"{x0:.3g}")
            p.drawText(QPointF(area.right() - 40, self.height() - 6), f"{x1:.3g}")
            p.drawText(QPointF(2, area.top() + 10), str(cmax))
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

    MEASURES = ("determinant", "condition_number")

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QVBoxLayout(self)
        row = QHBoxLayout()
        self.show_slice = QCheckBox("Slice")
        self.show_slice.toggled.connect(self.slice_toggled)
        self.measure = QComboBox()
        self.measure.addItems(list(self.MEASURES))
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
