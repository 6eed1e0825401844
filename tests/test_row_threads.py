"""Rows split into chunks for the thread pool: every row once, chunks on the kernel's grain."""

from __future__ import annotations

import multiprocessing
import os
import threading

import numba
import numpy as np
import pytest

from vhm_viz.core.row_threads import run_rows


def _recording_kernel(start, stop, counts, chunks, lock):
    counts[start:stop] += 1
    with lock:
        chunks.append((start, stop, threading.get_ident()))


@pytest.mark.parametrize("n_rows", [0, 1, 255, 256, 257, 1000, 4096, 10_001])
@pytest.mark.parametrize("threads", [1, 2])
def test_every_row_once_in_chunks_on_the_grain(n_rows, threads):
    before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    used = numba.get_num_threads()
    try:
        counts = np.zeros(n_rows, dtype=np.int64)
        chunks: list = []
        run_rows(_recording_kernel, n_rows, counts, chunks, threading.Lock(), grain=256)
    finally:
        numba.set_num_threads(before)
    assert np.all(counts == 1)
    starts = sorted(c[0] for c in chunks)
    assert all(s % 256 == 0 for s in starts)
    if used == 1 or n_rows <= 256:
        # one call, in the calling thread
        assert [(a, b) for a, b, _ in chunks] == [(0, n_rows)]
        assert chunks[0][2] == threading.get_ident()
    else:
        assert 1 < len(chunks) <= 4 * used
        assert threading.get_ident() not in {c[2] for c in chunks}


def test_a_compiled_kernel_gives_the_serial_result():
    @numba.njit(nogil=True)
    def squares(start, stop, x, out):
        for k in range(start, stop):
            out[k] = x[k] * x[k] + k

    x = np.random.default_rng(1).random(5000)
    out = np.full(5000, np.nan)
    run_rows(squares, len(x), x, out, grain=64)
    np.testing.assert_array_equal(out, x * x + np.arange(5000))


def test_a_kernel_error_reaches_the_caller():
    def failing(start, stop):
        if start > 0:
            raise ValueError(f"row {start}")

    before = numba.get_num_threads()
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    try:
        if numba.get_num_threads() < 2:
            pytest.skip("needs two threads")
        with pytest.raises(ValueError, match="row"):
            run_rows(failing, 4096, grain=256)
    finally:
        numba.set_num_threads(before)


def _fill_rows(start, stop, out):
    out[start:stop] = np.arange(start, stop)


def _child_fills(conn):
    out = np.zeros(4096)
    run_rows(_fill_rows, len(out), out, grain=256)
    conn.send(float(out.sum()))


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_a_forked_child_gets_working_threads():
    before = numba.get_num_threads()
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    try:
        run_rows(_fill_rows, 4096, np.zeros(4096), grain=256)  # the parent's pool exists
        ctx = multiprocessing.get_context("fork")
        receive, send = ctx.Pipe(duplex=False)
        child = ctx.Process(target=_child_fills, args=(send,))
        child.start()
        try:
            assert receive.poll(60), "the child's rows never ran"
            assert receive.recv() == float(np.arange(4096).sum())
        finally:
            child.join(10)
            if child.is_alive():
                child.kill()
    finally:
        numba.set_num_threads(before)
