"""Building and loading the C++ LSTM kernels: no stale lock, a bounded wait, signals honoured while waiting.

Every scenario runs in a subprocess with its own SEQTROJAN_CACHE and a timeout, so a regression fails instead of
hanging the suite. One test compiles the extension for real (about 100 s of CPU over its six sources); the others
never build.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from seqtrojan.agent import fast_lstm
from seqtrojan.errors import ConfigError, SeqTrojanError

ROOT = Path(__file__).resolve().parents[2]
WAIT = "SEQTROJAN_KERNEL_WAIT"  # the documented setting

LOAD = """
from seqtrojan.agent import fast_lstm
ext = fast_lstm.extension()
print("loaded" if ext is not None else f"unavailable: {fast_lstm.error()!r}")
"""

FALL_BACK = """
import torch
from seqtrojan.agent import fast_lstm
from seqtrojan.agent.network import RecurrentActorCritic

net = RecurrentActorCritic(6, 4)
obs = torch.zeros(3, 6)
with torch.no_grad():
    out = net.step(obs, net.initial_state(3))
print(type(fast_lstm.error()).__name__, fast_lstm.usable(obs), tuple(out.logits.shape))
"""

HOLD_AND_WAIT_TO_BE_KILLED = """
import fcntl, os, sys, time
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o644)
fcntl.flock(fd, fcntl.LOCK_EX)
print("locked", flush=True)
time.sleep(600)
"""


def _env(cache: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("SEQTROJAN_LSTM_BACKEND", WAIT)}
    env.update(SEQTROJAN_CACHE=str(cache), OMP_NUM_THREADS="1", **extra)
    return env


def _python(code: str, env: dict[str, str], timeout: float) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=ROOT, capture_output=True, text=True, timeout=timeout
    )


def _lock_file(build_dir: Path) -> Path:
    """The documented layout: the build lock of folder X is the file X.lock beside it."""
    return build_dir.with_name(build_dir.name + ".lock")


@contextlib.contextmanager
def _hold_lock(path: Path):
    """Hold the build lock in this process, as a live builder would."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        yield
    finally:
        os.close(fd)


def _messages(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("seqtrojan:")]


def test_leftovers_of_a_killed_build_do_not_block_the_next_one(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("SEQTROJAN_CACHE", str(cache))
    build_dir = fast_lstm._build_dir()
    # what torch's loader leaves when a build is killed part-way: its FileBaton 'lock' file in the build folder
    build_dir.mkdir(parents=True, exist_ok=True)
    (build_dir / "lock").write_text("")
    # and a builder SIGKILLed while it held the build lock
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD_AND_WAIT_TO_BE_KILLED, str(_lock_file(build_dir))],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
    finally:
        holder.kill()
        holder.wait(timeout=30)

    result = _python(LOAD, _env(cache, **{WAIT: "5"}), timeout=480)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "loaded", result.stderr
    assert (build_dir / "seqtrojan_fast_lstm.so").is_file()
    assert not (build_dir / "lock").exists()
    assert [p.name for p in cache.iterdir() if p.name.startswith(".")] == []  # no temporary build folder left

    # A built extension loads without the lock: a live holder does not delay it, and nothing is rebuilt.
    with _hold_lock(_lock_file(build_dir)):
        again = _python(LOAD, _env(cache, **{WAIT: "0"}), timeout=120)
    assert again.stdout.strip() == "loaded", again.stderr
    assert _messages(again.stderr) == []


def test_a_live_build_makes_another_process_wait_only_up_to_the_bound(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("SEQTROJAN_CACHE", str(cache))
    build_dir = fast_lstm._build_dir()
    lock = _lock_file(build_dir)
    with _hold_lock(lock):
        start = time.monotonic()
        result = _python(FALL_BACK, _env(cache, **{WAIT: "2"}), timeout=120)
        elapsed = time.monotonic() - start
    assert result.returncode == 0, result.stderr
    # the network ran on the PyTorch path after giving up
    assert result.stdout.split() == ["KernelBuildError", "False", "(3,", "4)"], result.stdout + result.stderr
    waiting, gave_up = _messages(result.stderr)
    assert str(lock) in waiting and "up to 2 s" in waiting and "PyTorch" in waiting
    assert "gave up after 2 s" in gave_up and "PyTorch" in gave_up
    assert elapsed >= 2
    assert not build_dir.exists()  # it did not build behind the holder's back


def test_build_lock_times_out_with_one_message(tmp_path, capsys):
    lock = tmp_path / "x.lock"
    with _hold_lock(lock):
        start = time.monotonic()
        with pytest.raises(fast_lstm.KernelBuildError, match=r"x\.lock") as info, fast_lstm.build_lock(lock, 0.3):
            pass
        assert time.monotonic() - start >= 0.3
    assert isinstance(info.value, SeqTrojanError)
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    with fast_lstm.build_lock(lock, timeout=0):  # free again once its holder lets go
        assert lock.read_text().strip() == str(os.getpid())


@pytest.mark.parametrize("value", ["soon", "-1", "nan"])
def test_a_malformed_wait_setting_is_an_error(monkeypatch, value):
    monkeypatch.setenv(WAIT, value)
    with pytest.raises(ConfigError, match=WAIT):
        fast_lstm.wait_seconds()


def test_sigterm_ends_a_training_run_that_waits_for_the_kernel_build(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("SEQTROJAN_CACHE", str(cache))
    command = [
        sys.executable, "-m", "seqtrojan.cli", "train", "--config", "configs/smoke.yaml",
        "--run.out-dir", str(tmp_path / "runs"), "--run.no-progress",
    ]  # fmt: skip
    with _hold_lock(_lock_file(fast_lstm._build_dir())):
        proc = subprocess.Popen(command, env=_env(cache, **{WAIT: "600"}), cwd=ROOT, stderr=subprocess.PIPE, text=True)
        lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=lambda: [lines.put(line) for line in proc.stderr], daemon=True).start()
        try:
            deadline = time.monotonic() + 120
            seen = ""
            while "is building the fast LSTM kernels" not in seen:
                assert proc.poll() is None, f"exited early: {seen}"
                try:
                    seen += lines.get(timeout=max(0.0, deadline - time.monotonic()))
                except queue.Empty:
                    pytest.fail(f"no 'waiting for the kernel build' message within 120 s: {seen!r}")
            time.sleep(0.5)
            proc.send_signal(signal.SIGTERM)
            try:
                code = proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                pytest.fail("SIGTERM did not end a run waiting for the kernel build lock")
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert code == -signal.SIGTERM


def _gomp_spin_count(**settings: str) -> str:
    """GOMP_SPINCOUNT as torch's libgomp reports it when ``seqtrojan`` is imported before torch."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    result = _python("import seqtrojan, torch", {**env, **settings, "OMP_DISPLAY_ENV": "VERBOSE"}, timeout=120)
    assert result.returncode == 0, result.stderr
    found = re.search(r"GOMP_SPINCOUNT = '(\d+)'", result.stderr)
    if found is None:
        pytest.skip("torch's OpenMP runtime is not libgomp")
    return found.group(1)


def test_openmp_threads_sleep_instead_of_spinning_unless_the_user_chose():
    assert _gomp_spin_count() == "0"  # OMP_WAIT_POLICY=PASSIVE: no spinning that a busy machine pays for
    assert _gomp_spin_count(GOMP_SPINCOUNT="300000") == "300000"
    assert _gomp_spin_count(OMP_WAIT_POLICY="ACTIVE") != "0"


def test_the_kernels_are_built_unless_the_pytorch_path_is_chosen():
    """About 80 kernel tests skip where the extension is unavailable; this one fails instead, so that a broken build
    cannot pass CI silently. ``SEQTROJAN_LSTM_BACKEND=torch`` says the PyTorch path is intended (then it skips)."""
    if os.environ.get("SEQTROJAN_LSTM_BACKEND") == "torch":
        pytest.skip("SEQTROJAN_LSTM_BACKEND=torch: the PyTorch path is intended")
    assert fast_lstm.extension() is not None, f"the C++ kernels did not build: {fast_lstm.error()}"
