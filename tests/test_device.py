"""Thread sharing among running commands (holowarp.device.cpu_threads)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from holowarp import device


@pytest.fixture
def runs_dir(tmp_path, monkeypatch):
    monkeypatch.setattr(device, "RUNS_DIR", str(tmp_path / "runs"))
    monkeypatch.delenv(device.THREADS_ENV, raising=False)
    device.set_cpu_threads(None)
    yield tmp_path / "runs"
    device.set_cpu_threads(None)


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_running_commands_share_the_cores_and_dead_ones_are_forgotten(runs_dir, monkeypatch):
    monkeypatch.setattr(device, "_available_cores", lambda: 4)
    assert device.live_runs() == 1  # no registry yet: this process alone
    with device.registered_run():
        assert (runs_dir / str(os.getpid())).is_file()
        assert device.live_runs() == 1 and device.cpu_threads() == 4
        (runs_dir / str(os.getppid())).touch()  # another live process
        dead = runs_dir / str(_dead_pid())
        dead.touch()
        (runs_dir / "notes.txt").touch()  # not a pid: ignored
        device.set_cpu_threads(None)  # forget the cached count
        assert device.live_runs() == 2 and device.cpu_threads() == 2
        assert not dead.exists()
    assert not (runs_dir / str(os.getpid())).exists()


def test_an_explicit_thread_count_wins_over_sharing(runs_dir, monkeypatch):
    monkeypatch.setattr(device, "_available_cores", lambda: 8)
    monkeypatch.setattr(device, "live_runs", lambda: 4)
    assert device.cpu_threads() == 2
    monkeypatch.setenv(device.THREADS_ENV, "3")
    device.set_cpu_threads(None)
    assert device.cpu_threads() == 3
    device.set_cpu_threads(5)
    assert device.cpu_threads() == 5
    monkeypatch.setenv(device.THREADS_ENV, "many")
    device.set_cpu_threads(None)
    with pytest.raises(device.DeviceError, match="HOLOWARP_THREADS"):
        device.cpu_threads()
    with pytest.raises(device.DeviceError, match=">= 1"):
        device.set_cpu_threads(0)
