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
    return IsolatedChild().call(func, *args, timeout=timeout, clean_exit=clean_exit, **kwargs)


class IsolatedChild:
    """The child interpreter of one ``call_isolated`` call, started now, called later: it imports
    the modules ``warm`` names (errors ignored: the call meets them again) while this process
    goes on, then waits for its call. Why: a mesh reader's import (trimesh and the SciPy modules
    it imports: ~0.4 s of one core) runs on the other core while a photo's retrieval runs here,
    instead of after it (``ucad_cl.fit``; a thread would share this process's GIL with the
    retrieval). ``call`` once (as ``call_isolated``); ``close`` kills a child never called (also
    on leaving a ``with`` block)."""

    def __init__(self, warm: tuple[str, ...] = ()):
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
        self._called = False
        self._send([p for p in sys.path if isinstance(p, str)], tuple(warm))

    def _send(self, *messages) -> None:
        try:
            assert self._proc.stdin is not None
            for m in messages:
                self._proc.stdin.write(pickle.dumps(m))
            self._proc.stdin.flush()
        except BrokenPipeError:
            pass                                    # the child died early: the call says so

    def call(self, func, *args, timeout: float, clean_exit: bool = False, **kwargs):
        """``func(*args, **kwargs)`` in the child, as ``call_isolated`` (``timeout`` counts
        from now, a warm import still running included)."""
        if not timeout > 0:
            raise ValueError(f"timeout must be > 0 seconds, got {timeout}")
        if self._called:
            raise RuntimeError("an IsolatedChild answers one call")
        self._called = True
        proc, conn = self._proc, self._conn
        try:
            self._send((func, args, kwargs, clean_exit))
            try:
                assert proc.stdin is not None
                proc.stdin.close()
            except BrokenPipeError:
                pass
            if not conn.poll(timeout):
                proc.kill()
                proc.wait()
                raise IsolatedCallFailed("timeout", f"did not finish within {timeout:g} s (killed)")
            try:
                kind, payload = conn.recv()
            except (EOFError, OSError):
                rc = proc.wait()
                how = f"killed by signal {signal.Signals(-rc).name}" if rc < 0 else f"exit code {rc}"
                raise IsolatedCallFailed("crashed", f"died ({how})") from None
        finally:
            conn.close()
            if proc.poll() is None:
                try:
                    proc.wait(timeout if clean_exit else 5.0)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        if kind == "raise":
            raise payload
        if kind != "ok":
            raise RuntimeError(payload)
        if clean_exit and proc.returncode != 0:
            rc = proc.returncode
            how = f"killed by signal {signal.Signals(-rc).name}" if rc < 0 else f"exit code {rc}"
            raise IsolatedCallFailed("crashed", f"answered, then died at exit ({how})")
        return payload

    def close(self) -> None:
        """Kill the child unless it was called (a called child has exited or been killed)."""
        if not self._called:
            self._called = True
            self._conn.close()
            if self._proc.poll() is None:
                self._proc.kill()
            self._proc.wait()
            if self._proc.stdin is not None:
                try:
                    self._proc.stdin.close()
                except BrokenPipeError:
                    pass

    def __enter__(self) -> "IsolatedChild":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def serve_isolated_call(fd: int) -> None:
    """Child side of ``IsolatedChild``: import the modules named on stdin (errors ignored),
    read (func, args, kwargs, clean_exit) on stdin, answer on ``fd``: ("ok", result), ("raise",
    exception) or ("error", "Type: message"); then, unless the parent checks how the child
    exits (``clean_exit``), leave at once (``os._exit``): the interpreter's own shutdown, which
    the parent would wait for, takes ~0.15 s once trimesh and SciPy are loaded."""
    clean_exit = True
    conn = Connection(fd, readable=False)
    try:
        for module in pickle.load(sys.stdin.buffer):
            try:
                importlib.import_module(module)
            except Exception:  # noqa: BLE001, S112 - the call imports it again and reports
                continue
        func, args, kwargs, clean_exit = pickle.load(sys.stdin.buffer)
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
