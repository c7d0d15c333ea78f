"""The step thread: one session core's gRPC Steps made on a thread of their own, so that a vector
env can send its Steps, let the trainer work, and collect the Batches later (``step_async`` /
``step_wait``). Over shared memory no thread is needed (:mod:`dinerdash._transport`). Why a
thread and not a grpcio future: docs/client.md#design-notes."""

from __future__ import annotations

import queue
import threading
import time
import weakref
from types import MethodType
from typing import Any

__all__ = ["StepThread"]


class StepThread:
    """A thread that makes one session core's blocking Step calls. It ends at :meth:`close`, or
    when the core whose method the work is is collected (the thread holds it weakly)."""

    __slots__ = ("_replies", "_reply", "_requests")

    def __init__(self, work: MethodType, name: str) -> None:
        self._requests: queue.SimpleQueue = queue.SimpleQueue()
        self._replies: queue.SimpleQueue = queue.SimpleQueue()
        self._reply: tuple[bool, Any] | None = None
        threading.Thread(
            target=_serve,
            args=(weakref.WeakMethod(work), self._requests, self._replies),
            name=name,
            daemon=True,
        ).start()
        weakref.finalize(work.__self__, self._requests.put, None)

    def submit(self, item: Any) -> None:
        self._requests.put(item)

    def wait(self, deadline: float | None = None) -> bool:
        """True when the reply is in by ``deadline`` (``None``: waits for it); it is then kept for
        :meth:`result`. An interrupted wait (Ctrl-C) loses nothing: the reply stays queued."""
        if self._reply is None:
            try:
                if deadline is None:
                    self._reply = self._replies.get()
                else:
                    self._reply = self._replies.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                return False
        return True

    def result(self) -> Any:
        """The work's return value for the oldest submitted item, or its exception raised."""
        reply = self._reply if self._reply is not None else self._replies.get()
        self._reply = None
        ok, value = reply
        if ok:
            return value
        raise value

    def close(self) -> None:
        self._requests.put(None)


def _serve(work: weakref.WeakMethod, requests: queue.SimpleQueue, replies: queue.SimpleQueue):
    while (item := requests.get()) is not None:
        method = work()
        if method is None:
            return
        try:
            replies.put((True, method(item)))
        except BaseException as e:
            replies.put((False, e))
        del method
