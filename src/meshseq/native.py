"""The numpy roll-out's compiled pieces, built and loaded without torch.

``predict`` and ``complete`` run the generator in numpy (``meshseq.numpy_net``) so that a command
does not pay torch's import. Their mesh-conv layers are most of a diverse completion's time in
numpy (a sparse product, two GEMMs of 9 columns, the bias and tanh: about ten passes over the
frames); ``csrc/inference.cpp`` does a layer in one pass, as the training kernel does, and holds
the encoder's FC product (``fc_wx``) and a tiled transpose of the frames. They are plain C
functions: built on first use with the system's C++ compiler (``CXX``, else ``c++``; about 1 s)
into ``MESHSEQ_KERNEL_DIR`` (default ``~/.cache/meshseq``), one build per source and CPU kind,
and called through ``ctypes``.

``MESHSEQ_CPU_KERNELS=0`` turns it off (as the training kernels); without a compiler, or when the
build fails, numpy_net runs its numpy layers, after one warning.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import warnings
from pathlib import Path

import numpy as np

_CSRC = Path(__file__).resolve().parent / "csrc"
_SOURCE = _CSRC / "inference.cpp"
_HEADERS = [_CSRC / "simd.h", _CSRC / "conv_forward.h", _CSRC / "fc_forward.h"]
_FLAGS = ["-O3", "-march=native", "-shared", "-fPIC", "-std=c++17", "-pthread"]
#: the most channels a layer of the compiled convolution takes (``csrc/conv_forward.h``)
MAX_CHANNELS = 16

_lock = threading.Lock()
_library: ctypes.CDLL | None | bool = None  # None: not tried yet; False: unavailable


def cpu_signature(cpuinfo: str | None = None) -> str:
    """8 hex digits naming this CPU's instruction sets (the ``flags`` of ``/proc/cpuinfo``; elsewhere
    the platform's processor name), part of a build's name.

    The kernels are compiled with ``-march=native``: a build made on a CPU with AVX-512 would
    crash (illegal instruction) when loaded on one without, e.g. from a home folder shared by
    the nodes of a cluster, so each kind of CPU gets its own build. ``cpuinfo``: the text of
    ``/proc/cpuinfo`` (read when None).
    """
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    flags = next((line.split(":", 1)[1] for line in cpuinfo.splitlines() if line.startswith(("flags", "Features"))), None)
    key = " ".join(sorted(flags.split())) if flags else f"{platform.machine()} {platform.processor()}"
    return hashlib.sha1(key.encode()).hexdigest()[:8]


def build_path() -> Path:
    """Where this source, these flags and this kind of CPU have their build."""
    root = os.environ.get("MESHSEQ_KERNEL_DIR") or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "meshseq"
    digest = hashlib.sha1(b"".join(p.read_bytes() for p in [_SOURCE, *_HEADERS]) + " ".join(_FLAGS).encode())
    return Path(root) / f"inference-{digest.hexdigest()[:12]}-{cpu_signature()}.so"


def _build(target: Path) -> None:
    """Compile into a temporary file beside ``target`` and move it into place (a concurrent build or
    a killed one never leaves a half-written library under the final name)."""
    compiler = os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++")
    if not compiler:
        raise RuntimeError("no C++ compiler (c++, g++ or $CXX) found")
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(fd)
    try:
        done = subprocess.run([compiler, *_FLAGS, "-I", str(_CSRC), str(_SOURCE), "-o", tmp],
                              capture_output=True, text=True)
        if done.returncode:
            raise RuntimeError(" ".join(done.stderr.split())[:300])
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def conv_library() -> ctypes.CDLL | None:
    """The compiled layer (built on the first call), or None: turned off, or it could not be built
    (one warning, saying why)."""
    global _library
    if _library is None:
        with _lock:
            if _library is None:
                _library = _load() or False
    return _library or None


def _load() -> ctypes.CDLL | None:
    if os.environ.get("MESHSEQ_CPU_KERNELS", "1") == "0":
        return None
    try:
        path = build_path()
        if not path.is_file():
            _build(path)
        lib = ctypes.CDLL(str(path))
    except Exception as e:  # no compiler, a compile error, an unwritable cache: numpy's layers, say why
        warnings.warn(f"meshseq: the compiled mesh convolution could not be built ({type(e).__name__}: {e}); "
                      "synthesis uses numpy's slower layers", RuntimeWarning, stacklevel=3)
        return None
    f = lib.meshseq_conv_vcb
    p = ctypes.c_void_p
    f.argtypes = [p, p, p, p, p, ctypes.c_int64, p, p, p, ctypes.c_int64] + [ctypes.c_int] * 5
    f.restype = ctypes.c_int
    lib.meshseq_fc_wx.argtypes = [p] * 5 + [ctypes.c_int64, ctypes.c_int64, ctypes.c_int, ctypes.c_int]
    lib.meshseq_fc_wx.restype = None
    t = lib.meshseq_transpose
    t.argtypes = [p, ctypes.c_int64, p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64, ctypes.c_int]
    t.restype = None
    return lib


class CompiledRing:
    """The ring matrix ``A`` (a scipy CSR) as the compiled layer reads it: int64 indices, float32."""

    def __init__(self, ring):
        self.rowptr = np.ascontiguousarray(ring.indptr, dtype=np.int64)
        self.col = np.ascontiguousarray(ring.indices, dtype=np.int64)
        self.weight = np.ascontiguousarray(ring.data, dtype=np.float32)


def padded_chains(b: int) -> int:
    """The chains a layer of ``b`` runs: a whole tile of SIMD lanes (8, or a multiple of 16)."""
    return 8 if b <= 8 else -(-b // 16) * 16


def conv(lib: ctypes.CDLL, x: np.ndarray, w_self: np.ndarray, w_ring: np.ndarray, bias: np.ndarray,
         ring: CompiledRing, act: bool, threads: int = 0) -> np.ndarray:
    """``act(W_s x + W_r (A x) + b)`` for channel-major frames ``x`` ``(V, C_in, Bp)`` float32 (``Bp``
    = ``padded_chains``) -> ``(V, C_out, Bp)``; ``W_s``, ``W_r`` ``(C_out, C_in)``, ``b`` ``(C_out,)``
    or per vertex ``(V, C_out)``, all float32 and contiguous; ``threads``: how many share the vertices (0: one)."""
    V, C, B = x.shape
    C_out = w_self.shape[0]
    y = np.empty((V, C_out, B), dtype=np.float32)
    stride = C_out if bias.ndim == 2 else 0
    ptr = lambda a: a.ctypes.data  # noqa: E731
    status = lib.meshseq_conv_vcb(ptr(x), ptr(y), ptr(w_self), ptr(w_ring), ptr(bias), stride, ptr(ring.rowptr),
                                  ptr(ring.col), ptr(ring.weight), V, B, C, C_out, int(act), int(threads))
    if status:
        raise ValueError(f"the compiled mesh convolution takes at most {MAX_CHANNELS} channels and 8 or a multiple "
                         f"of 16 chains, got {C} -> {C_out} channels, {B} chains")
    return y


def transpose(lib: ctypes.CDLL, a: np.ndarray, out: np.ndarray, threads: int = 0) -> np.ndarray:
    """``out[...] = a.T`` for 2-D float32 ``a`` ``(rows, cols)`` and ``out`` ``(cols, rows)``, each with
    unit stride along its last axis (any row stride: a column block of a wider array)."""
    if a.dtype != np.float32 or out.dtype != np.float32 or a.strides[1] != 4 or out.strides[1] != 4 \
            or out.shape != a.shape[::-1]:
        raise ValueError(f"transpose: float32 rows of unit stride, (r, c) -> (c, r); got {a.shape} -> {out.shape}")
    lib.meshseq_transpose(a.ctypes.data, a.strides[0] // 4, out.ctypes.data, out.strides[0] // 4, a.shape[0],
                          a.shape[1], int(threads))
    return out


#: columns of the FC weight per partial sum of ``fc_wx`` (``csrc/fc_forward.h``'s NCHUNK_COLS)
FC_CHUNK = 2048


def _check_fc(weight: np.ndarray, cols: np.ndarray, rows: int) -> None:
    if weight.dtype != np.float32 or cols.dtype != np.float32 or not (weight.flags.c_contiguous
                                                                       and cols.flags.c_contiguous):
        raise ValueError("fc: contiguous float32 arrays")
    if cols.ndim != 2 or cols.shape[0] != rows or cols.shape[1] % 8:
        raise ValueError(f"fc: columns ({rows}, a multiple of 8) expected, got {cols.shape}")


def fc_wx(lib: ctypes.CDLL, weight: np.ndarray, x: np.ndarray, bias: np.ndarray, threads: int = 0) -> np.ndarray:
    """``W x + b`` ``(L, B)`` for the FC weight ``W`` ``(L, N)`` and columns ``x`` ``(N, B)`` (B a multiple of 8):
    one stream over ``W``, each weight broadcast against a SIMD vector of the columns."""
    L, N = weight.shape
    _check_fc(weight, x, N)
    B = x.shape[1]
    out = np.empty((L, B), dtype=np.float32)
    partial = np.empty(((N + FC_CHUNK - 1) // FC_CHUNK, L, B), dtype=np.float32)
    lib.meshseq_fc_wx(weight.ctypes.data, x.ctypes.data, np.ascontiguousarray(bias, np.float32).ctypes.data,
                      out.ctypes.data, partial.ctypes.data, L, N, B, int(threads))
    return out
