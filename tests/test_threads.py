"""Thread counts from affinity, cgroup quotas, MPI ranks and the user's settings."""

from __future__ import annotations

import os
import subprocess
import sys

import numba
import pytest

from vhm_viz.core.threads import available_cpus, cgroup_cpu_limit, thread_count, use_threads


def _cgroup_tree(tmp_path, membership, files):
    tmp_path.mkdir(parents=True, exist_ok=True)
    proc = tmp_path / "cgroup"
    proc.write_text(membership)
    for rel, text in files.items():
        path = tmp_path / "fs" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return tmp_path / "fs", proc


def test_cgroup_v2_quota_of_the_process_group(tmp_path):
    root, proc = _cgroup_tree(
        tmp_path, "0::/job/task\n", {"job/task/cpu.max": "150000 100000\n", "cpu.max": "max 1"}
    )
    assert cgroup_cpu_limit(root, proc) == pytest.approx(1.5)


def test_cgroup_v2_without_quota_and_at_the_mount_root(tmp_path):
    root, proc = _cgroup_tree(tmp_path, "0::/\n", {"cpu.max": "max 100000\n"})
    assert cgroup_cpu_limit(root, proc) is None
    root, proc = _cgroup_tree(tmp_path / "b", "0::/x\n", {"cpu.max": "300000 100000\n"})
    assert cgroup_cpu_limit(root, proc) == pytest.approx(3.0)


def test_cgroup_v1_cfs_quota(tmp_path):
    root, proc = _cgroup_tree(
        tmp_path,
        "12:memory:/a\n4:cpu,cpuacct:/a\n",
        {"cpu,cpuacct/a/cpu.cfs_quota_us": "200000", "cpu,cpuacct/a/cpu.cfs_period_us": "100000"},
    )
    assert cgroup_cpu_limit(root, proc) == pytest.approx(2.0)
    root, proc = _cgroup_tree(
        tmp_path / "b",
        "4:cpu,cpuacct:/a\n",
        {"cpu,cpuacct/a/cpu.cfs_quota_us": "-1", "cpu,cpuacct/a/cpu.cfs_period_us": "100000"},
    )
    assert cgroup_cpu_limit(root, proc) is None


def test_no_cgroup_files_means_no_limit(tmp_path):
    assert cgroup_cpu_limit(tmp_path, tmp_path / "missing") is None


def test_available_cpus_follow_the_affinity_mask():
    # a child pinned to one CPU sees one, whatever the machine has
    first = min(os.sched_getaffinity(0))
    code = (
        f"import os; os.sched_setaffinity(0, {{{first}}}); "
        "from vhm_viz.core.threads import available_cpus; print(available_cpus())"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "1"
    assert 1 <= available_cpus() <= len(os.sched_getaffinity(0))


def test_thread_count_precedence_and_ranks(monkeypatch):
    monkeypatch.delenv("VHM_THREADS", raising=False)
    cpus = available_cpus()
    assert thread_count() == cpus
    assert thread_count(ranks_on_machine=2) == max(1, cpus // 2)
    assert thread_count(ranks_on_machine=10 * cpus) == 1
    monkeypatch.setenv("VHM_THREADS", "3")
    assert thread_count() == 3
    assert thread_count(5) == 5
    for bad in ("0", "-2", "two", "1.5"):
        monkeypatch.setenv("VHM_THREADS", bad)
        with pytest.raises(ValueError, match="VHM_THREADS must be a positive integer"):
            thread_count()
    with pytest.raises(ValueError, match="positive integer"):
        thread_count(0)


def test_use_threads_sets_numba_and_caps_at_its_pool(monkeypatch):
    monkeypatch.delenv("VHM_THREADS", raising=False)
    before = numba.get_num_threads()
    try:
        assert use_threads(1) == 1 and numba.get_num_threads() == 1
        big = numba.config.NUMBA_NUM_THREADS + 5
        assert use_threads(big) == numba.config.NUMBA_NUM_THREADS
    finally:
        numba.set_num_threads(before)


@pytest.mark.parametrize(("setting", "expected"), [(None, 1), ("2", 2)])
def test_a_command_gives_blas_one_thread_unless_asked(setting, expected):
    """After a command's thread set-up every loaded BLAS (numpy's and scipy's OpenBLAS)
    runs ``VHM_BLAS_THREADS`` threads, one by default: its spinning pool beside numba's
    kernels or another busy process made a small QR many times slower."""
    code = (
        "import scipy.linalg, threadpoolctl\n"
        "from vhm_viz.core.threads import use_threads\n"
        "use_threads()\n"
        "print(sorted({i['num_threads'] for i in threadpoolctl.threadpool_info()"
        " if i['user_api'] == 'blas'}))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "VHM_BLAS_THREADS"}
    if setting is not None:
        env["VHM_BLAS_THREADS"] = setting
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"[{expected}]"


def test_a_bad_blas_thread_count_is_one_line():
    env = dict(os.environ, VHM_BLAS_THREADS="many")
    done = subprocess.run(
        [sys.executable, "-m", "vhm_viz.cli", "cage", "--help"], capture_output=True, env=env
    )
    assert done.returncode == 0  # help needs no threads
    done = subprocess.run(
        [sys.executable, "-m", "vhm_viz.cli", "deform", "nothing.vti", "--scene", "s.json",
         "-o", "o.vts"],
        capture_output=True, text=True, env=env,
    )  # fmt: skip
    assert done.returncode != 0 and "Traceback" not in done.stderr
    assert "VHM_BLAS_THREADS must be a positive integer; got 'many'" in done.stderr
