"""Optional CPU accelerator for the masked LSTM stack: fused C++ forward/BPTT kernels (``csrc/fast_lstm.cpp``).

The same kernels serve a peephole LSTM layer (:func:`unroll_peephole_layer`, :func:`step_peephole_layer`) and,
in ``csrc/gru.cpp``, a GRU layer (:func:`unroll_gru_layer`, :func:`step_gru_layer`); all are one extension.

Why: on a 2-core CPU, PyTorch's per-op dispatch and per-op thread fork/join dominate a step-by-step LSTM. The
kernels split the batch into one block per thread and run the whole time loop of a block on its thread: one
GEMM per step on ``[x_t | h_{t-1} * mask | 1]``, fused gate math, and a hand-written BPTT that accumulates the
weight gradients while each step's data is still in cache. Measured on this project's 2-core Zen 4 machine:
about 520k samples/s forward + backward for the paper's 54 -> 64 -> 32 network versus about 280k/s for the
PyTorch path (see benchmarks/train_throughput.py).

The extension is compiled once per machine on first use (about a minute on 2 cores; needs a C++ compiler, which the
PyTorch CPU wheels already require for this) into ``~/.cache/seqtrojan`` (``SEQTROJAN_CACHE`` overrides), in a folder
keyed by the sources (the bytes of every file in ``csrc`` and their path), the Python environment (``sys.prefix``), the
torch version and the CPU, so that two clones or virtual environments never share one. A build runs in a fresh temporary
folder under an ``fcntl.flock`` lock of our own and is renamed into place when complete: a killed build leaves neither a
half-built extension nor a lock (the kernel drops a dead process's flock), and loading a built extension takes no lock
at all. A process that finds another one building waits up to ``SEQTROJAN_KERNEL_WAIT`` seconds (default 300), saying so
on stderr, and then uses the PyTorch path. Where it cannot be built, or on CUDA, or when an intervention must see every
step, :mod:`seqtrojan.agent.network` uses its PyTorch path, which computes the same function.
``SEQTROJAN_LSTM_BACKEND=torch`` disables the extension.

Semantics are exactly those of the PyTorch path (tested, including gradcheck in float64). Activations in
float32 use inline approximations with about 3e-7 maximum error, the size of float32 rounding.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import os
import platform
import shutil
import sys
import tempfile
import threading
import time
import weakref
from pathlib import Path
from types import ModuleType

import torch
from torch.autograd.function import once_differentiable

from seqtrojan.errors import ConfigError, SeqTrojanError

try:
    import fcntl
except ImportError:  # not POSIX: no build lock, and the PyTorch path is used
    fcntl = None  # type: ignore[assignment]

_CSRC = Path(__file__).parent / "csrc"
# One extension for all cells: fast_lstm.cpp (LSTM, peephole LSTM and the Python module), gru.cpp,
# band_attention.cpp, layer_norm.cpp, bias_relu.cpp and window_step.cpp (the Transformer's attention, norms, MLP
# activation and rollout step), sparse_input.cpp (a first layer's product with a one-hot observation), common.h.
_SOURCES = tuple(_CSRC / name for name in ("fast_lstm.cpp", "gru.cpp", "band_attention.cpp", "layer_norm.cpp",
                                           "bias_relu.cpp", "window_step.cpp", "sparse_input.cpp"))  # fmt: skip
_HEADERS = (_CSRC / "common.h",)
_NAME = "seqtrojan_fast_lstm"
# -fopenmp is required: at::parallel_for is an inline OpenMP template (without it the batch blocks run one after
# another). -ffast-math at compile time only: linking with it would set flush-to-zero for the whole process.
_CFLAGS = ("-O3", "-march=native", "-ffast-math", "-fopenmp")
_LDFLAGS = ("-fopenmp",)
WAIT_ENV = "SEQTROJAN_KERNEL_WAIT"
DEFAULT_WAIT_S = 300.0
_POLL_S = 0.1
_lock = threading.Lock()
_ext: ModuleType | None = None
_error: Exception | None = None


class KernelBuildError(SeqTrojanError):
    """The fast LSTM kernels are unavailable in this process (the PyTorch path is used instead)."""


# ---------------------------------------------------------------------------------------------- loading
def _cpu_signature() -> str:
    try:
        text = Path("/proc/cpuinfo").read_text()
        fields = [ln for ln in text.splitlines() if ln.startswith(("model name", "flags"))][:2]
        return "\n".join(fields)
    except OSError:
        return platform.processor()


def cache_root() -> Path:
    """The folder holding the compiled kernels: ``$SEQTROJAN_CACHE``, else ``~/.cache/seqtrojan``."""
    return Path(os.environ.get("SEQTROJAN_CACHE") or Path.home() / ".cache" / "seqtrojan")


def _build_dir() -> Path:
    """The folder of the built extension for this source, environment, torch and CPU (it may not exist yet)."""
    parts: list[bytes | str] = [
        *(part for path in _SOURCES + _HEADERS for part in (path.name, path.read_bytes())),
        str(_CSRC.resolve()),  # two clones never share (or fight over) one folder
        sys.prefix,  # nor do two virtual environments
        torch.__version__,
        str(Path(torch.__file__).resolve().parent),
        sys.version,
        platform.machine(),
        _cpu_signature(),
        " ".join(_CFLAGS + _LDFLAGS),
    ]
    key = hashlib.sha256(b"\0".join(p if isinstance(p, bytes) else p.encode() for p in parts)).hexdigest()[:16]
    return cache_root() / f"fast_lstm_{key}"


def _lock_path(build_dir: Path) -> Path:
    return build_dir.with_name(build_dir.name + ".lock")


def wait_seconds() -> float:
    """How long to wait for another process's build: ``$SEQTROJAN_KERNEL_WAIT`` seconds, default 300."""
    text = os.environ.get(WAIT_ENV, "").strip()
    if not text:
        return DEFAULT_WAIT_S
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not value >= 0:  # also rejects nan
        raise ConfigError(f"{WAIT_ENV} must be a number of seconds >= 0, got {text!r}")
    return value


@contextlib.contextmanager
def build_lock(path: Path, timeout: float):
    """Hold an exclusive ``flock`` on ``path`` (created if missing) for the ``with`` block.

    If another process holds it, say so in one line on stderr and poll for up to ``timeout`` seconds, then raise
    :class:`KernelBuildError`. The wait sleeps in short steps, so signals (SIGTERM, Ctrl-C) act at once. The lock
    cannot go stale: the kernel releases it when its holder exits, however it exits."""
    if fcntl is None:
        raise KernelBuildError("no fcntl.flock on this platform to guard the kernel build")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        if not _try_flock(fd):
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            print(
                f"seqtrojan: another process (pid {holder}) is building the fast LSTM kernels (lock {path}); "
                f"waiting up to {timeout:g} s ({WAIT_ENV}), then this run uses the PyTorch LSTM path",
                file=sys.stderr,
                flush=True,
            )
            deadline = time.monotonic() + timeout
            while not _try_flock(fd):
                left = deadline - time.monotonic()
                if left <= 0:
                    raise KernelBuildError(
                        f"gave up after {timeout:g} s waiting for the kernel build lock {path} (held by pid {holder})"
                    )
                time.sleep(min(_POLL_S, left))
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock


def _try_flock(fd: int) -> bool:
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def _import_built(build_dir: Path):
    """The extension module from a complete build folder, or None if there is none."""
    so = build_dir / f"{_NAME}.so"
    if not so.is_file():
        return None
    spec = importlib.util.spec_from_file_location(_NAME, so)
    if spec is None or spec.loader is None:
        raise KernelBuildError(f"cannot import the fast LSTM kernels from {so}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _build(build_dir: Path):
    """Compile into a fresh temporary folder and rename it to ``build_dir``; the caller holds the build lock."""
    from torch.utils.cpp_extension import load

    # Leftovers of killed builds (no live builder exists while we hold the lock), including torch's 'lock' baton.
    for old in build_dir.parent.glob(f".{build_dir.name}.build-*"):
        shutil.rmtree(old, ignore_errors=True)
    print("seqtrojan: compiling the C++ kernels (once per machine, about a minute)...", file=sys.stderr, flush=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{build_dir.name}.build-", dir=build_dir.parent))
    try:
        module = load(
            name=_NAME,
            sources=[str(path) for path in _SOURCES],
            extra_cflags=list(_CFLAGS),
            extra_ldflags=list(_LDFLAGS),
            build_directory=str(tmp),
            verbose=False,
        )
        os.chmod(tmp, 0o755)  # mkdtemp makes it private
        if build_dir.exists():  # an incomplete folder (no extension in it), e.g. from an older seqtrojan
            shutil.rmtree(build_dir)
        os.rename(tmp, build_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # a failed build (after a rename, tmp no longer exists)
    return module


def _load_or_build():
    build_dir = _build_dir()
    module = _import_built(build_dir)
    if module is not None:
        return module
    with build_lock(_lock_path(build_dir), wait_seconds()):
        module = _import_built(build_dir)  # built by the process we waited for
        return module if module is not None else _build(build_dir)


def extension():
    """The compiled extension, building it on first use; None where it cannot be built (reason: ``error()``)."""
    global _ext, _error
    if _ext is not None or _error is not None:
        return _ext
    with _lock:
        if _ext is not None or _error is not None:
            return _ext
        if os.environ.get("SEQTROJAN_LSTM_BACKEND", "auto") == "torch":
            _error = RuntimeError("disabled by SEQTROJAN_LSTM_BACKEND=torch")
            return None
        wait_seconds()  # a malformed setting is an error, not a silent fallback
        try:
            _ext = _load_or_build()
        except KernelBuildError as err:
            _error = err
            print(f"seqtrojan: {err}; using the PyTorch LSTM path", file=sys.stderr, flush=True)
        except Exception as err:  # the toolchain or the BLAS symbols are missing: use the PyTorch path
            _error = err
    return _ext


def error() -> Exception | None:
    """Why the extension is unavailable (None if it loaded or was not tried yet)."""
    return _error


def usable(x: torch.Tensor) -> bool:
    """The extension applies to this input (CPU, float32/float64) and is built."""
    return x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64) and extension() is not None


def num_chunks(batch: int) -> int:
    """One batch block per intra-op thread (tiny batches are not split)."""
    return max(1, min(torch.get_num_threads(), batch // 16))


# ---------------------------------------------------------------------------------------------- buffers
# Buffers over 32 MB come from mmap and are unmapped on free, so every fresh allocation page-faults on first
# touch (10-35% of a forward + backward at large T * B). Internal buffers are therefore recycled: a buffer is
# returned to the pool only when the autograd graph that owns it is freed, so retain_graph stays correct.
_POOL: dict[tuple, list[torch.Tensor]] = {}
_POOL_LOCK = threading.RLock()
_POOL_MAX_PER_KEY = 4


def _pool_get(shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
    with _POOL_LOCK:
        free = _POOL.get((tuple(shape), dtype))
        if free:
            return free.pop()
    return torch.empty(shape, dtype=dtype)


def _pool_put(*tensors: torch.Tensor) -> None:
    with _POOL_LOCK:
        for t in tensors:
            free = _POOL.setdefault((tuple(t.shape), t.dtype), [])
            if len(free) < _POOL_MAX_PER_KEY:
                free.append(t)


def clear_pool() -> None:
    """Drop the recycled buffers (frees their memory)."""
    with _POOL_LOCK:
        _POOL.clear()


class _Releaser:
    """Returns buffers to the pool when the autograd context holding it is garbage-collected."""

    __slots__ = ("buffers",)

    def __init__(self, *buffers: torch.Tensor) -> None:
        self.buffers = buffers

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            _pool_put(*self.buffers)


# ---------------------------------------------------------------------------------------------- GEMM matrices
def _lstm_weight(w_ih: torch.Tensor, w_hh: torch.Tensor, b_ih: torch.Tensor, b_hh: torch.Tensor) -> torch.Tensor:
    """The (4H, I+H+1) GEMM matrix ``[W_ih | W_hh | b_ih + b_hh]`` of one LSTM step (plain or peephole)."""
    return torch.cat([w_ih, w_hh, (b_ih + b_hh).unsqueeze(1)], 1).contiguous()


def _gru_weight(w_ih: torch.Tensor, w_hh: torch.Tensor, b_ih: torch.Tensor, b_hh: torch.Tensor) -> torch.Tensor:
    """The (4H, I+H+1) GEMM matrix of one GRU step, rows r, z, n_x, n_h (see csrc/gru.cpp).

    n = tanh(n_x + r * n_h) needs the input and the hidden part of the new gate apart, hence four row blocks
    where nn.GRUCell has three: ``[W_ir|W_hr|b_ir+b_hr], [W_iz|W_hz|b_iz+b_hz], [W_in|0|b_in], [0|W_hn|b_hn]``."""
    hidden, n_in = w_hh.shape[1], w_ih.shape[1]
    h2, h3 = 2 * hidden, 3 * hidden
    wc = w_ih.new_zeros(4 * hidden, n_in + hidden + 1)
    wc[:h3, :n_in] = w_ih
    wc[:h2, n_in:-1] = w_hh[:h2]
    wc[h3:, n_in:-1] = w_hh[h2:]
    wc[:h2, -1] = b_ih[:h2] + b_hh[:h2]
    wc[h2:h3, -1] = b_ih[h2:]
    wc[h3:, -1] = b_hh[h2:]
    return wc


# ---------------------------------------------------------------------------------------------- sparse inputs
SPARSE_MIN_INPUTS = 128
"""inputs narrower than this always take the dense product (the grid world's 54: one GEMM is cheaper)"""
SPARSE_MAX_DENSITY = 0.2
"""the largest share of nonzero entries for which :func:`sparse_project` beats the dense product here (MiniGrid's
one-hot view: 0.15)"""


def is_sparse_input(x: torch.Tensor) -> bool:
    """Whether a layer's input is worth projecting by :func:`sparse_project`: an observation (no gradient wanted
    for it) of at least :data:`SPARSE_MIN_INPUTS` numbers, at most :data:`SPARSE_MAX_DENSITY` of them nonzero."""
    if x.requires_grad or x.shape[-1] < SPARSE_MIN_INPUTS or x.numel() == 0:
        return False
    return int(torch.count_nonzero(x)) <= SPARSE_MAX_DENSITY * x.numel()


class _SparseProjection(torch.autograd.Function):
    """``x @ w.T`` for a mostly-zero ``x`` (N, I) that needs no gradient, differentiable in ``w`` (G, I)."""

    @staticmethod
    def forward(ctx, x, w):
        x = x.contiguous()
        out = x.new_empty(x.shape[0], w.shape[0])
        assert _ext is not None  # callers run only after extension() loaded it
        _ext.sparse_project(x, w.t().contiguous(), out)
        ctx.save_for_backward(x)
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, d_out):
        (x,) = ctx.saved_tensors
        if not ctx.needs_input_grad[1]:
            return None, None
        d_wt = d_out.new_empty(x.shape[1], d_out.shape[1])
        assert _ext is not None  # callers run only after extension() loaded it
        _ext.sparse_project_grad(x, d_out.contiguous(), d_wt)
        return None, d_wt.t()


def sparse_project(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """``x @ w.T`` reading only the nonzero entries of ``x`` (N, I), which gets no gradient; ``w`` (G, I) does.

    For a one-hot observation (MiniGrid's view: 500 numbers, 75 ones) this replaces the first layer's dense product,
    the largest part of a training step on such envs; the sums run in another order than the GEMM's, so results
    agree with the dense product to float rounding, not bit for bit."""
    return _SparseProjection.apply(x, w)


# ---------------------------------------------------------------------------------------------- autograd
class _MaskedLSTMLayer(torch.autograd.Function):
    """One LSTM layer over T steps; the state is multiplied by ``keep[t]`` before step t.

    With ``peephole`` (3, H) it is the peephole LSTM of :func:`unroll_peephole_layer`; None is the plain LSTM
    (the kernels compile the peephole terms out, so the plain path is not slowed)."""

    @staticmethod
    def forward(ctx, x, keep, h0, c0, w_ih, w_hh, b_ih, b_hh, return_c_seq: bool, peephole=None, projected=None):
        steps, batch, n_in = x.shape
        hidden = w_hh.shape[1]
        k = n_in + hidden + 1
        dtype = x.dtype
        wc = _lstm_weight(w_ih, w_hh, b_ih, b_hh)  # (4H, K)
        xh = _pool_get((steps, batch, k), dtype)
        gates = _pool_get((steps, batch, 4 * hidden), dtype)
        c_prev = _pool_get((steps, batch, hidden), dtype)
        c_seq = x.new_empty(steps, batch, hidden) if return_c_seq else _pool_get((steps, batch, hidden), dtype)
        h_seq = x.new_empty(steps, batch, hidden)
        peep = None if peephole is None else peephole.contiguous()
        assert _ext is not None  # callers run only after extension() loaded it
        _ext.lstm_fwd_cat(
            x.contiguous(), keep, h0.contiguous(), c0.contiguous(), wc, peep, xh, gates, h_seq, c_seq, c_prev,
            num_chunks(batch), None if projected is None else projected.contiguous(),
        )  # fmt: skip
        # c_seq is an output when return_c_seq: kept on ctx as an attribute it would make a reference cycle
        # (output -> grad_fn -> ctx -> output) that frees only with the cyclic GC: measured, a state-camouflage
        # training grew by ~145 MB per update until it held 22 GB. Outputs go through save_for_backward.
        if return_c_seq:
            ctx.save_for_backward(keep, w_ih, w_hh, peep, c_seq)
            ctx.buffers = (wc, xh, gates, None, c_prev)
        else:
            ctx.save_for_backward(keep, w_ih, w_hh, peep, None)
            ctx.buffers = (wc, xh, gates, c_seq, c_prev)
        pooled = (xh, gates, c_prev) if return_c_seq else (xh, gates, c_seq, c_prev)
        ctx.releaser = _Releaser(*pooled)
        ctx.return_c_seq = return_c_seq
        ctx.projected = projected is not None
        ctx.set_materialize_grads(False)
        if return_c_seq:
            return h_seq, c_seq
        return h_seq, c_seq[steps - 1].clone()

    @staticmethod
    @once_differentiable
    def backward(ctx, d_h_seq, d_c):
        keep, w_ih, _w_hh, peep, output_c = ctx.saved_tensors
        wc, xh, gates, c_seq, c_prev = ctx.buffers
        c_seq = output_c if ctx.return_c_seq else c_seq
        steps, batch, four_h = gates.shape
        hidden = four_h // 4
        n_in = w_ih.shape[1]
        k = n_in + hidden + 1
        d_h_seq = gates.new_zeros(steps, batch, hidden) if d_h_seq is None else d_h_seq.contiguous()
        d_c_seq, d_c_last = None, gates.new_zeros(batch, hidden)
        if d_c is not None:
            if ctx.return_c_seq:
                d_c_seq = d_c.contiguous()
            else:
                d_c_last = d_c.contiguous()
        need = ctx.needs_input_grad
        dx = gates.new_empty(steps, batch, n_in) if need[0] else None
        chunks = num_chunks(batch)
        dw_parts = gates.new_empty(chunks, four_h, k)
        dp_parts = None if peep is None else gates.new_empty(chunks, 3, hidden)
        dh0 = gates.new_empty(batch, hidden)
        dc0 = gates.new_empty(batch, hidden)
        d_projected = gates.new_empty(steps, batch, four_h) if ctx.projected and need[10] else None
        assert _ext is not None  # callers run only after extension() loaded it
        _ext.lstm_bwd_cat(
            gates, c_seq, c_prev, keep, wc, peep, xh, n_in, d_h_seq, d_c_seq, d_c_last, dx, dw_parts, dp_parts, dh0,
            dc0, d_projected,
        )  # fmt: skip
        dwc = dw_parts.sum(0) if chunks > 1 else dw_parts[0]  # (4H, K)
        dw_ih = dwc[:, :n_in].contiguous() if need[4] else None
        dw_hh = dwc[:, n_in : n_in + hidden].contiguous() if need[5] else None
        db = dwc[:, k - 1].contiguous()
        dpeep = dp_parts.sum(0) if dp_parts is not None and need[9] else None
        return (
            dx, None, dh0 if need[2] else None, dc0 if need[3] else None, dw_ih, dw_hh,
            db if need[6] else None, db if need[7] else None, None, dpeep, d_projected,
        )  # fmt: skip


class _MaskedGRULayer(torch.autograd.Function):
    """One GRU layer over T steps; the state is multiplied by ``keep[t]`` before step t."""

    @staticmethod
    def forward(ctx, x, keep, h0, w_ih, w_hh, b_ih, b_hh, projected=None):
        steps, batch, n_in = x.shape
        hidden = w_hh.shape[1]
        dtype = x.dtype
        wc = _gru_weight(w_ih, w_hh, b_ih, b_hh)  # (4H, K)
        xh = _pool_get((steps, batch, n_in + hidden + 1), dtype)
        gates = _pool_get((steps, batch, 4 * hidden), dtype)
        h_seq = x.new_empty(steps, batch, hidden)
        assert _ext is not None  # callers run only after extension() loaded it
        _ext.gru_fwd_cat(
            x.contiguous(), keep, h0.contiguous(), wc, xh, gates, h_seq, num_chunks(batch),
            None if projected is None else projected.contiguous(),
        )  # fmt: skip
        # backward reads h_{t-1} from xh, so h_seq (an output) is not saved: no reference cycle through ctx
        ctx.save_for_backward(keep)
        ctx.buffers = (wc, xh, gates)
        ctx.releaser = _Releaser(xh, gates)
        ctx.n_in = n_in
        ctx.projected = projected is not None
        ctx.set_materialize_grads(False)
        return h_seq

    @staticmethod
    @once_differentiable
    def backward(ctx, d_h_seq):
        (keep,) = ctx.saved_tensors
        wc, xh, gates = ctx.buffers
        steps, batch, four_h = gates.shape
        hidden, n_in = four_h // 4, ctx.n_in
        h2, h3, k = 2 * hidden, 3 * hidden, n_in + hidden + 1
        d_h_seq = gates.new_zeros(steps, batch, hidden) if d_h_seq is None else d_h_seq.contiguous()
        need = ctx.needs_input_grad
        dx = gates.new_empty(steps, batch, n_in) if need[0] else None
        chunks = num_chunks(batch)
        dw_parts = gates.new_empty(chunks, four_h, k)
        dh0 = gates.new_empty(batch, hidden)
        d_projected = gates.new_empty(steps, batch, four_h) if ctx.projected and need[7] else None
        assert _ext is not None  # callers run only after extension() loaded it
        _ext.gru_bwd_cat(gates, keep, wc, xh, n_in, d_h_seq, dx, dw_parts, dh0, d_projected)
        dwc = dw_parts.sum(0) if chunks > 1 else dw_parts[0]  # (4H, K), rows r, z, n_x, n_h
        dw_ih = dwc[:h3, :n_in].contiguous() if need[3] else None
        dw_hh = torch.cat([dwc[:h2, n_in : k - 1], dwc[h3:, n_in : k - 1]]) if need[4] else None
        db_ih = dwc[:h3, k - 1].contiguous() if need[5] else None
        db_hh = torch.cat([dwc[:h2, k - 1], dwc[h3:, k - 1]]) if need[6] else None
        return dx, None, dh0 if need[2] else None, dw_ih, dw_hh, db_ih, db_hh, d_projected


def unroll_layer(cell: torch.nn.LSTMCell, x, keep, h0, c0, return_c_seq: bool):
    """(T, B, I) through one layer; returns (h_seq (T, B, H), c_seq (T, B, H) or final c (B, H))."""
    return _unroll_lstm(cell, x, keep, h0, c0, return_c_seq, None)


def _unroll_lstm(cell: torch.nn.Module, x, keep, h0, c0, return_c_seq: bool, peephole):
    """A plain (``peephole`` None) or peephole LSTM layer over (T, B, I); a mostly-zero input that needs no
    gradient (a one-hot observation) is projected by :func:`sparse_project` and the kernel runs on the rest."""
    w_ih, w_hh, b_ih, b_hh = (_param(cell, name) for name in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"))
    if not is_sparse_input(x):
        return _MaskedLSTMLayer.apply(x, keep, h0, c0, w_ih, w_hh, b_ih, b_hh, return_c_seq, peephole, None)
    steps, batch, _ = x.shape
    projected = sparse_project(x.reshape(steps * batch, -1), w_ih).view(steps, batch, -1)
    no_input, no_weight = x.new_empty(steps, batch, 0), w_ih.detach().new_empty(w_ih.shape[0], 0)
    return _MaskedLSTMLayer.apply(
        no_input, keep, h0, c0, no_weight, w_hh, b_ih, b_hh, return_c_seq, peephole, projected
    )  # fmt: skip


def _param(module: torch.nn.Module, name: str) -> torch.Tensor:
    """``module.<name>`` as a tensor (typed: nn.Module attributes are untyped)."""
    value = getattr(module, name)
    assert isinstance(value, torch.Tensor)
    return value


def unroll_peephole_layer(
    cell: torch.nn.Module,
    x: torch.Tensor,
    keep: torch.Tensor,
    h0: torch.Tensor,
    c0: torch.Tensor,
    return_c_seq: bool,
) -> tuple[torch.Tensor, torch.Tensor]:
    """A peephole LSTM layer over (T, B, I), as :func:`unroll_layer`; differentiable also w.r.t. ``cell.peephole``.

    ``cell`` holds nn.LSTMCell's four tensors and ``peephole`` (3, H) = rows (p_i, p_f, p_o); with the masked
    state cp = c_{t-1} * keep[t]: i = sig(z_i + p_i cp), f = sig(z_f + p_f cp), o = sig(z_o + p_o c_t)."""
    return _unroll_lstm(cell, x, keep.contiguous(), h0, c0, return_c_seq, _param(cell, "peephole"))


def unroll_gru_layer(
    cell: torch.nn.Module, x: torch.Tensor, keep: torch.Tensor, h0: torch.Tensor, return_states: bool
) -> torch.Tensor:
    """A GRU layer (nn.GRUCell's tensors) over (T, B, I); returns h_seq (T, B, H), differentiable w.r.t. x, h0
    and the weights.

    ``return_states`` is accepted so that callers treat every cell alike; it changes nothing here, because the
    GRU's whole state is h, which h_seq already holds at every step."""
    del return_states
    w_ih, w_hh, b_ih, b_hh = (_param(cell, name) for name in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"))
    if not is_sparse_input(x):
        return _MaskedGRULayer.apply(x, keep.contiguous(), h0, w_ih, w_hh, b_ih, b_hh, None)
    steps, batch, _ = x.shape
    projected = _gru_projection(x.reshape(steps * batch, -1), w_ih).view(steps, batch, -1)
    no_input, no_weight = x.new_empty(steps, batch, 0), w_ih.detach().new_empty(w_ih.shape[0], 0)
    return _MaskedGRULayer.apply(no_input, keep.contiguous(), h0, no_weight, w_hh, b_ih, b_hh, projected)


def _gru_projection(x: torch.Tensor, w_ih: torch.Tensor) -> torch.Tensor:
    """A GRU kernel's projected input (N, 4H): rows r, z, n_x from :func:`sparse_project`, n_h zero."""
    projected = sparse_project(x, w_ih)  # (N, 3H)
    return torch.cat([projected, projected.new_zeros(projected.shape[0], projected.shape[1] // 3)], 1)


# ---------------------------------------------------------------------------------------------- inference steps
@torch.no_grad()
def step_stack(cells, x, keep, states, weight_cache: dict):
    """One no-grad step of all layers in one call; ``states`` is a list of (h, c). Returns new (h, c) per layer.

    A one-hot observation (:func:`is_sparse_input`) is projected by :func:`sparse_project` for the first layer,
    whose kernel step then multiplies only ``[h | 1]``."""
    sparse = is_sparse_input(x)
    wcs, projected = [], None
    for i, cell in enumerate(cells):
        params = (cell.weight_ih, cell.weight_hh, cell.bias_ih, cell.bias_hh)
        split = sparse and i == 0
        key = (split, *((id(p), p._version) for p in params))  # optimizer steps and load_state_dict bump versions
        if weight_cache.get(id(cell), (None,))[0] != key:
            if split:  # [W_hh | b] for the kernel, W_ih^T for the projection
                built = (_lstm_weight(params[0][:, :0], *params[1:]), params[0].t().contiguous())
            else:
                built = (_lstm_weight(*params), None)
            weight_cache[id(cell)] = (key, built)
        wc, w_t = weight_cache[id(cell)][1]
        wcs.append(wc)
        if w_t is not None:
            projected = x.new_empty(x.shape[0], w_t.shape[1])
            assert _ext is not None  # callers run only after extension() loaded it
            _ext.sparse_project(x.contiguous(), w_t, projected)
    hs = [h.contiguous() for h, _ in states]
    cs = [c.contiguous() for _, c in states]
    out_h = [torch.empty_like(h) for h in hs]
    out_c = [torch.empty_like(c) for c in cs]
    x_in = x.new_empty(x.shape[0], 0) if projected is not None else x.contiguous()
    assert _ext is not None  # callers run only after extension() loaded it
    _ext.lstm_stack_step(
        x_in, keep.contiguous(), hs, cs, wcs, [], out_h, out_c, num_chunks(x.shape[0]), projected
    )  # fmt: skip
    return list(zip(out_h, out_c))


# The GEMM matrix of a cell for the one-layer steps below, rebuilt when a parameter is replaced or changed in
# place (optimizer steps and load_state_dict bump ``_version``). Weakly keyed: it dies with its cell.
_STEP_WEIGHTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _step_weight(cell: torch.nn.Module, build, kind: str) -> torch.Tensor:
    """``build(*cell's four tensors)``, cached per cell and ``kind`` (the matrix ``build`` makes) until a parameter
    is replaced or changed."""
    params = (cell.weight_ih, cell.weight_hh, cell.bias_ih, cell.bias_hh)
    versions = tuple(p._version for p in params)
    try:
        kinds = _STEP_WEIGHTS.setdefault(cell, {})
    except TypeError:  # a cell that takes no weak reference: no cache
        return build(*params)
    cached = kinds.get(kind)
    if cached is None or cached[1] != versions or any(a is not b for a, b in zip(cached[0], params)):
        cached = (params, versions, build(*params))
        kinds[kind] = cached
    return cached[2]


@torch.no_grad()
def step_peephole_layer(
    cell: torch.nn.Module, x: torch.Tensor, keep: torch.Tensor, h: torch.Tensor, c: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """One no-grad step of one peephole LSTM layer; ``keep`` (B,) multiplies (h, c) first. Returns (h, c)."""
    h, c = h.contiguous(), c.contiguous()
    out_h, out_c = torch.empty_like(h), torch.empty_like(c)
    wc = _step_weight(cell, _lstm_weight, "lstm")
    assert _ext is not None  # callers run only after extension() loaded it
    _ext.lstm_stack_step(
        x.contiguous(), keep.contiguous(), [h], [c], [wc], [_param(cell, "peephole").contiguous()], [out_h], [out_c],
        num_chunks(x.shape[0]), None,
    )  # fmt: skip
    return out_h, out_c


@torch.no_grad()
def step_gru_layer(cell: torch.nn.Module, x: torch.Tensor, keep: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """One no-grad step of one GRU layer; ``keep`` (B,) multiplies h first. Returns the new h. A one-hot input
    (:func:`is_sparse_input`) is projected by :func:`sparse_project`, the kernel multiplies ``[h | 1]`` only."""
    h = h.contiguous()
    out_h = torch.empty_like(h)
    projected = None
    if is_sparse_input(x):
        wc = _step_weight(cell, lambda w_ih, *rest: _gru_weight(w_ih[:, :0], *rest), "gru without input")
        projected = _gru_projection(x, _param(cell, "weight_ih"))
        x = x.new_empty(x.shape[0], 0)
    else:
        wc = _step_weight(cell, _gru_weight, "gru")
    assert _ext is not None  # callers run only after extension() loaded it
    _ext.gru_stack_step(
        x.contiguous(), keep.contiguous(), [h], [wc], [out_h], num_chunks(x.shape[0]), projected
    )  # fmt: skip
    return out_h
