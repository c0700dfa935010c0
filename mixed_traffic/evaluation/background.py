"""A rollout in a second process while this one goes on: the evaluation's two independent halves on two cores.

A checkpoint's evaluation runs the policy's rollout and, on the same episodes, a classical reference controller's
(``eval.reference``). Neither reads the other, and at these batch sizes each rollout keeps one core busy with
per-step overhead, so on a 2-core machine the reference runs in a forked child beside the policy's rollout
(``eval.parallel_reference``). The numbers are the same to the bit: every row draws from a generator seeded by its
episode (:func:`mixed_traffic.evaluation.harness.seed_episodes`), in whichever process it runs.

Why not ``concurrent.futures`` or ``torch.multiprocessing``: both pickle the callable, and the reference's
policy factory is a closure over the parsed controller; a forked child inherits it as it is. Where ``fork`` is not
available (Windows), is unsafe (CUDA initialised in this process) or the caller asks for it, the call runs here
instead, after the caller's own work, with the same result.

>>> job = Background(lambda: sum(range(10)))
>>> job.result()
45
"""

from __future__ import annotations

import multiprocessing as mp
import traceback
from collections.abc import Callable
from typing import Any

import torch


def can_fork() -> bool:
    """Whether a forked child may run torch code here (``fork`` exists and CUDA is not initialised)."""
    return "fork" in mp.get_all_start_methods() and not torch.cuda.is_initialized()


def _child(fn: Callable[[], Any], conn) -> None:
    torch.set_num_threads(1)  # the parent keeps its own core; as TorchRL's and DataLoader's workers do
    try:
        out = ("ok", fn())
    except BaseException as e:  # noqa: BLE001 - everything goes back to the parent, which raises it
        out = ("error", f"{type(e).__name__}: {e}\n{traceback.format_exc()}")
    conn.send(out)
    conn.close()


class Background:
    """``fn()`` in a forked child process, started now; :meth:`result` waits for its return value.

    ``fn`` takes no arguments and returns something picklable. With ``enabled=False`` (or where :func:`can_fork`
    is false) nothing is started and :meth:`result` calls ``fn`` itself. An exception in the child is raised
    again by :meth:`result` (as a ``RuntimeError`` that carries the child's traceback); a child that dies
    without an answer (killed, out of memory) is reported with its exit code.
    """

    def __init__(self, fn: Callable[[], Any], *, enabled: bool = True, name: str = "background rollout"):
        self.fn, self.name = fn, name
        self.proc = None
        if enabled and can_fork():
            recv, send = mp.get_context("fork").Pipe(duplex=False)
            self.proc = mp.get_context("fork").Process(target=_child, args=(fn, send), name=name, daemon=True)
            self.proc.start()
            send.close()  # the child holds the only sending end: EOF here once it exits
            self.conn = recv

    @property
    def forked(self) -> bool:
        """Whether ``fn`` runs in a child process (False: :meth:`result` runs it here)."""
        return self.proc is not None

    def result(self) -> Any:
        if self.proc is None:
            return self.fn()
        try:
            status, value = self.conn.recv()
        except EOFError:
            self.proc.join()
            raise RuntimeError(f"{self.name}: the child process ended without an answer "
                               f"(exit code {self.proc.exitcode})") from None
        finally:
            self.conn.close()
        self.proc.join()
        if status == "error":
            raise RuntimeError(f"{self.name} failed in its child process: {value}")
        return value

    def cancel(self) -> None:
        """Stop the child (the caller failed and will not read the result)."""
        if self.proc is not None and self.proc.is_alive():
            self.proc.terminate()
            self.proc.join()
