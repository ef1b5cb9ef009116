"""Small host utilities the driver, the engines and the commands share: printable paths, the
default worker memory limit, process memory from /proc (MB), and ``call_isolated`` (a function
run in a fresh child interpreter; ``IsolatedChild``: that child started before the call)."""
from __future__ import annotations

import importlib
import os
import pickle
import signal
import subprocess
import sys
from multiprocessing.connection import Connection


#: what ``ingest.load_mesh`` imports: a mesh reader's child (``IsolatedChild(warm=...)``)
#: imports these ahead (here, not in ``ingest``, so that the CLI can start such a child before
#: importing anything heavy)
READER_MODULES = ("ucad_cl.ingest", "trimesh")
#: what those warm imports go without: trimesh imports SciPy's ``spatial`` and ``optimize`` as
#: it loads (over half of its import: ~0.8 of 1.4 s of a core on a slow Zen 4) for functions a
#: mesh read never calls, and treats SciPy as optional (such a function raises when called).
#: Hidden for the warm import only: a later ``import scipy`` (the orientation's) loads it.
READER_HIDDEN = ("scipy",)


def reader_child() -> "IsolatedChild":
    """A mesh reader's child: ``IsolatedChild`` warming ``READER_MODULES`` with
    ``READER_HIDDEN`` hidden (``ingest.MeshLoader``; the CLI's ``fit`` starts one first)."""
    return IsolatedChild(warm=READER_MODULES, hide=READER_HIDDEN)


def reader_modules_loaded() -> bool:
    """Whether this process has imported ``READER_MODULES`` already (then a mesh is read here,
    no child is started for it)."""
    return all(m in sys.modules for m in READER_MODULES)


def printable(text: str) -> str:
    """``text`` as valid UTF-8 for logs and terminals: bytes of a non-UTF-8 file name (Python's
    surrogate escapes) are written ``\\xNN``."""
    try:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:
        return text.encode("utf-8", "backslashreplace").decode("utf-8")


def default_memory_limit_mb(workers: int) -> float:
    """Half the machine's memory divided among the workers, at least 1 GiB each."""
    try:
        import psutil
        total = psutil.virtual_memory().total
    except ImportError:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    return max(1024.0, total / 2**20 / 2 / max(1, workers))


def tree_rss_mb() -> float:
    """Resident memory of this process and its children (MB); 0 without psutil."""
    try:
        import psutil
    except ImportError:
        return 0.0
    total = 0
    try:
        me = psutil.Process()
        for p in [me] + me.children(recursive=True):
            try:
                total += p.memory_info().rss
            except psutil.Error:
                pass
    except psutil.Error:
        return 0.0
    return total / 2**20


def process_memory_mb(pid: int) -> tuple[float, float, float]:
    """(VmRSS, VmHWM, VmData) of a process in MB from /proc; zeros where unavailable. VmHWM is
    the peak of the process' own memory (unlike ``ru_maxrss``, which after fork + exec starts at
    the parent's size)."""
    out = {"VmRSS": 0.0, "VmHWM": 0.0, "VmData": 0.0}
    try:
        with open(f"/proc/{pid}/status", "rb") as f:
            for line in f:
                key, _, value = line.partition(b":")
                k = key.decode()
                if k in out:
                    out[k] = int(value.split()[0]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return out["VmRSS"], out["VmHWM"], out["VmData"]


# ----------------------------------------------------------------------------- isolated calls

class IsolatedCallFailed(RuntimeError):
    """The child of ``call_isolated`` gave no answer: ``kind`` is "timeout" (still running after
    the timeout, killed) or "crashed" (died); ``how`` says which signal, exit code or timeout."""

    def __init__(self, kind: str, how: str):
        self.kind, self.how = kind, how
        super().__init__(f"the child process {how}")


def call_isolated(func, *args, timeout: float, clean_exit: bool = False, **kwargs):
    """``func(*args, **kwargs)`` in a fresh child interpreter; its return value, or the exception
    it raised, raised again here.

    Used where a native library may crash or hang on what it is given (mesh loaders), or where
    loading it would stay in this process's memory for good (the build driver checks the
    segmenter and probes the OpenCL devices this way: ~150 MB for PoCL and its LLVM, ~60 MB for
    an onnxruntime session, never freed). ``func`` must be a module-level function; arguments,
    result and exception must pickle (an exception that does not comes back as RuntimeError
    "Type: message"). The child is ``python -c`` (not multiprocessing 'spawn', which re-runs the
    caller's ``__main__`` and breaks scripts without a main guard) with this process's
    ``sys.path`` and environment; the call goes in on stdin, the answer comes back on a dedicated
    pipe (native libraries may write to stdout). ``IsolatedCallFailed`` when the child dies
    without answering or runs past ``timeout`` seconds (then it is killed); with ``clean_exit``,
    also when it answers and then exits abnormally (LLVM aborting at exit, say). ``func`` may be
    given as ``"module:function"``, imported only in the child. ``IsolatedChild`` starts the
    child before the call is known.
    """
    if not timeout > 0:
        raise ValueError(f"timeout must be > 0 seconds, got {timeout}")
    with IsolatedChild() as child:
        return child.call(func, *args, timeout=timeout, clean_exit=clean_exit, **kwargs)


class IsolatedChild:
    """A child interpreter for isolated calls (``call_isolated`` makes one call in a new one),
    started now: it imports the modules ``warm`` names (errors ignored: a call meets them again;
    any module ``hide`` names is unimportable meanwhile, as if not installed, and importable
    again after) while this process goes on, then answers ``call``s one at a time until
    ``close`` (also on leaving a ``with`` block). Why: a mesh reader's import (trimesh: ~0.5 s
    of one core with SciPy hidden, ~1.3 s with it, on a slow Zen 4) runs beside a photo's
    retrieval instead of after it, and a batch of photos pays it once
    (``ucad_cl.ingest.MeshLoader``; a thread would share this process's GIL with the retrieval).
    A call that crashes the child or runs past its timeout ends it (``alive`` is then False and
    later calls raise ``IsolatedCallFailed``); a call with ``clean_exit`` is the last: the child
    exits and its exit status is checked. ``submit`` starts a call ahead (the child runs it
    while this process goes on); the ``call`` with the same arguments then collects its
    answer."""

    def __init__(self, warm: tuple[str, ...] = (), hide: tuple[str, ...] = ()):
        read_fd, write_fd = os.pipe()
        code = ("import pickle, sys; sys.path[:0] = pickle.load(sys.stdin.buffer); "
                "from ucad_cl.system import serve_isolated_call; "
                "serve_isolated_call(int(sys.argv[1]))")
        try:
            self._proc = subprocess.Popen([sys.executable, "-c", code, str(write_fd)],
                                          pass_fds=(write_fd,), stdin=subprocess.PIPE,
                                          stdout=subprocess.DEVNULL)
        except BaseException:
            os.close(read_fd)
            raise
        finally:
            os.close(write_fd)
        self._conn = Connection(read_fd, writable=False)
        self._calls = 0
        self._closed = False
        self._pending: tuple | None = None      # (func, args, kwargs) submitted, not collected
        self._send([p for p in sys.path if isinstance(p, str)], tuple(warm), tuple(hide))

    @property
    def alive(self) -> bool:
        """Whether the child can still take a call."""
        return not self._closed and self._proc.poll() is None

    def _send(self, *messages, last: bool = False) -> None:
        stdin = self._proc.stdin
        assert stdin is not None
        try:
            for m in messages:
                stdin.write(pickle.dumps(m))
            stdin.flush()
            if last:
                stdin.close()
        except BrokenPipeError:
            pass                                    # the child died: the call says so

    def _died(self) -> IsolatedCallFailed:
        rc = self._proc.wait()
        how = f"killed by signal {signal.Signals(-rc).name}" if rc < 0 else f"exit code {rc}"
        return IsolatedCallFailed("crashed", f"died ({how})")

    def submit(self, func, *args, **kwargs) -> None:
        """Start ``func(*args, **kwargs)`` in the child now, without waiting; ``call`` with the
        same arguments collects its answer (its timeout counts from that call). One at a time:
        any other call before that is a RuntimeError. A child that died takes no call: the
        collecting ``call`` says so."""
        if self._closed:
            raise RuntimeError("this IsolatedChild is closed")
        if self._pending is not None:
            raise RuntimeError("a submitted call is not collected yet")
        self._pending = (func, args, kwargs)
        if self._proc.poll() is None:
            self._calls += 1
            self._send((func, args, kwargs, False))

    def call(self, func, *args, timeout: float, clean_exit: bool = False, **kwargs):
        """``func(*args, **kwargs)`` in the child, as ``call_isolated`` (``timeout`` counts
        from now, a warm import still running included), or the answer of that same call
        ``submit``ted earlier."""
        if not timeout > 0:
            raise ValueError(f"timeout must be > 0 seconds, got {timeout}")
        if self._closed:
            raise RuntimeError("this IsolatedChild is closed")
        proc, conn = self._proc, self._conn
        if self._pending is not None:
            if self._pending != (func, args, kwargs) or clean_exit:
                raise RuntimeError("a different call was submitted and is not collected yet")
            self._pending = None
            if proc.poll() is not None and not conn.poll(0):
                raise self._died()
        else:
            if proc.poll() is not None:
                raise self._died()
            self._calls += 1
            self._send((func, args, kwargs, clean_exit), last=clean_exit)
        if not conn.poll(timeout):
            proc.kill()
            proc.wait()
            raise IsolatedCallFailed("timeout", f"did not finish within {timeout:g} s (killed)")
        try:
            kind, payload = conn.recv()
        except (EOFError, OSError):
            raise self._died() from None
        if clean_exit:
            try:
                rc = proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                rc = proc.wait()
            self.close()
            if kind == "ok" and rc != 0:
                how = (f"killed by signal {signal.Signals(-rc).name}" if rc < 0
                       else f"exit code {rc}")
                raise IsolatedCallFailed("crashed", f"answered, then died at exit ({how})")
        if kind == "raise":
            raise payload
        if kind != "ok":
            raise RuntimeError(payload)
        return payload

    def close(self) -> None:
        """End the child: one never called, or running a submitted call nobody collected, is
        killed; one called is told to leave (it does at once) and killed if it has not within
        5 s."""
        if self._closed:
            return
        self._closed = True
        proc = self._proc
        if proc.poll() is None and (not self._calls or self._pending is not None):
            proc.kill()
        try:
            assert proc.stdin is not None
            proc.stdin.close()
        except BrokenPipeError:
            pass
        try:
            proc.wait(5.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        self._conn.close()

    def __enter__(self) -> "IsolatedChild":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def serve_isolated_call(fd: int) -> None:
    """Child side of ``IsolatedChild``: import the modules named on stdin (errors ignored), with
    those named next hidden (``None`` in ``sys.modules``: their import raises
    ``ModuleNotFoundError``) until the imports are done, then read calls (func, args, kwargs,
    clean_exit) on stdin until it closes, answering each on ``fd``: ("ok", result), ("raise",
    exception) or ("error", "Type: message"); then, unless the last call asked for a clean exit
    (its status is checked), leave at once (``os._exit``): the interpreter's own shutdown, which
    the parent would wait for, takes ~0.15 s once trimesh and SciPy are loaded."""
    conn = Connection(fd, readable=False)
    clean_exit = False
    warm, hide = pickle.load(sys.stdin.buffer), pickle.load(sys.stdin.buffer)
    hidden = [name for name in hide if name not in sys.modules]
    sys.modules.update(dict.fromkeys(hidden))
    for module in warm:
        try:
            importlib.import_module(module)
        except Exception:  # noqa: BLE001, S112 - a call imports it again and reports
            continue
    for name in hidden:
        if sys.modules.get(name, 0) is None:
            del sys.modules[name]
    while True:
        try:
            func, args, kwargs, clean_exit = pickle.load(sys.stdin.buffer)
        except EOFError:
            break
        except BaseException as e:  # noqa: BLE001 - an unreadable call: said, then the end
            conn.send(("error", f"the call cannot be read ({type(e).__name__}: {e})"))
            break
        result = _answer(func, args, kwargs)
        try:
            conn.send(result)
        except Exception as e:  # noqa: BLE001 - a result that does not pickle
            conn.send(("error", f"the result of the isolated call does not pickle "
                                f"({type(e).__name__}: {e})"))
    conn.close()
    if not clean_exit:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(0)


def _answer(func, args, kwargs) -> tuple:
    """What ``serve_isolated_call`` sends back for one call: the result, or the exception (as
    text when it does not pickle)."""
    try:
        if isinstance(func, str):                   # "module:function"
            module, name = func.split(":")
            func = getattr(importlib.import_module(module), name)
        result: tuple = ("ok", func(*args, **kwargs))
    except BaseException as e:  # noqa: BLE001 - everything goes back to the parent
        try:
            pickle.loads(pickle.dumps(e))
            result = ("raise", e)
        except Exception:  # noqa: BLE001 - an exception that does not pickle goes back as text
            result = ("error", f"{type(e).__name__}: {e}")
    return result
