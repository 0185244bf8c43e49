"""Messages between the MPI ranks of ParaView (``mpiexec -n N pvbatch`` / ``pvserver``).

A :class:`Communicator` moves two kinds of payload between ranks:

* a dict of numpy arrays (:meth:`~Communicator.send` / :meth:`~Communicator.recv` /
  :meth:`~Communicator.broadcast`), packed into one byte buffer: a JSON header with each
  array's name, dtype and shape, then the raw bytes;
* small JSON-able records (:meth:`~Communicator.gather`, :meth:`~Communicator.allgather`)
  and numbers (:meth:`~Communicator.allreduce_min_max`, :meth:`~Communicator.allreduce_max`).

Every collective is built on the two point-to-point primitives ``_send_bytes`` /
``_recv_bytes`` (root <-> others, rank order), so the three implementations only differ there:

:class:`VTKCommunicator`
    ParaView's own MPI: the global ``vtkMultiProcessController`` (``vtkMPIController`` under
    ``mpiexec``), ``Send``/``Receive`` of a ``vtkUnsignedCharArray``.  ParaView's VTK must be
    the one imported (pvbatch/pvserver); the module imports it only when asked.
:class:`SerialCommunicator`
    One rank: collectives return their input, point-to-point raises.
:func:`local_group`
    ``n`` communicators of one process joined by queues, for running the ranks' code in
    threads (tests, and checking a distributed algorithm without MPI).

:func:`communicator` returns the VTK one when ParaView runs several ranks, else the serial one.
All ranks must call a collective in the same order (as with MPI).

Examples
--------
>>> import threading
>>> group = local_group(2)
>>> out = {}
>>> def rank(c):
...     lo, hi = c.allreduce_min_max(c.rank * 10.0, c.rank * 10.0 + 1)
...     got = c.broadcast({"x": np.arange(3.0)} if c.rank == 0 else None)
...     out[c.rank] = (lo, hi, got["x"].tolist(), c.gather({"rank": c.rank}))
>>> threads = [threading.Thread(target=rank, args=(c,)) for c in group]
>>> for t in threads:
...     t.start()
>>> for t in threads:
...     t.join()
>>> out[0]
(0.0, 11.0, [0.0, 1.0, 2.0], [{'rank': 0}, {'rank': 1}])
>>> out[1][3] is None
True
"""

from __future__ import annotations

import json
import os
import queue
import resource
import struct
import sys
import time
from contextlib import contextmanager

import numpy as np

from dvr_perception.errors import DVRInputError

__all__ = [
    "Communicator",
    "RankFailure",
    "SerialCommunicator",
    "VTKCommunicator",
    "abort_on_error",
    "communicator",
    "local_group",
    "pack_arrays",
    "peak_rss_mb",
    "unpack_arrays",
]

#: MPI tags of this module's messages: far from ParaView's own (its RMI tags are < 1000).
TAG_ARRAYS = 171_701
TAG_BCAST = 171_702
TAG_GATHER = 171_703
TAG_REDUCE = 171_704


def pack_arrays(arrays: dict) -> np.ndarray:
    """Pack a dict ``name -> array`` into one uint8 buffer (see :func:`unpack_arrays`).

    Examples
    --------
    >>> buf = pack_arrays({"a": np.arange(4, dtype=np.uint32).reshape(2, 2), "b": np.ones(1)})
    >>> got = unpack_arrays(buf)
    >>> got["a"].tolist(), got["a"].dtype.name, got["b"].tolist()
    ([[0, 1], [2, 3]], 'uint32', [1.0])
    """
    header, chunks = [], []
    for name, value in arrays.items():
        a = np.asarray(value)
        a = np.ascontiguousarray(a) if a.ndim else a.reshape(())  # keeps 0-d arrays 0-d
        if a.dtype.hasobject:
            raise DVRInputError(f"pack_arrays: {name!r} holds Python objects, not numbers")
        header.append([str(name), a.dtype.str, list(a.shape)])
        chunks.append(a.reshape(-1).view(np.uint8))
    head = json.dumps(header).encode()
    return np.concatenate([np.frombuffer(struct.pack("<Q", len(head)) + head, np.uint8), *chunks])


def unpack_arrays(buffer) -> dict:
    """Unpack a buffer of :func:`pack_arrays` into its dict of arrays (each its own copy)."""
    buf = np.ascontiguousarray(buffer, dtype=np.uint8).reshape(-1)
    (n,) = struct.unpack("<Q", buf[:8].tobytes())
    pos = 8 + n
    out = {}
    for name, dtype, shape in json.loads(buf[8:pos].tobytes().decode()):
        dt = np.dtype(dtype)
        size = dt.itemsize * int(np.prod(shape, dtype=np.int64))
        out[name] = buf[pos : pos + size].view(dt).reshape(tuple(shape)).copy()
        pos += size
    if pos != buf.size:
        raise DVRInputError(f"unpack_arrays: {buf.size - pos} bytes left over (corrupt message)")
    return out


def _json_bytes(obj) -> np.ndarray:
    return np.frombuffer(json.dumps(obj).encode(), np.uint8)


def _from_json_bytes(buf: np.ndarray):
    return json.loads(np.asarray(buf, np.uint8).tobytes().decode())


class Communicator:
    """Operations between ``size`` ranks; this object is rank :attr:`rank`.

    Subclasses provide ``_send_bytes(buffer, dest, tag)`` and ``_recv_bytes(source, tag)``
    (a uint8 array each way).
    """

    rank: int = 0
    size: int = 1

    # -- point to point ----------------------------------------------------------------------
    def _send_bytes(self, buffer: np.ndarray, dest: int, tag: int) -> None:
        raise NotImplementedError

    def _recv_bytes(self, source: int, tag: int) -> np.ndarray:
        raise NotImplementedError

    def _check_peer(self, other: int, what: str) -> int:
        other = int(other)
        if not (0 <= other < self.size) or other == self.rank:
            raise DVRInputError(
                f"{what}: rank {other} is not another rank of 0..{self.size - 1} (this is "
                f"rank {self.rank})"
            )
        return other

    def send(self, arrays: dict, dest: int, tag: int = TAG_ARRAYS) -> None:
        """Send a dict of numpy arrays to rank ``dest`` (blocking until it is handed over)."""
        self._send_bytes(pack_arrays(arrays), self._check_peer(dest, "send"), tag)

    def recv(self, source: int, tag: int = TAG_ARRAYS) -> dict:
        """Receive the dict of arrays rank ``source`` sent with :meth:`send`."""
        return unpack_arrays(self._recv_bytes(self._check_peer(source, "recv"), tag))

    # -- collectives (every rank calls them, in the same order) -----------------------------
    def broadcast(self, arrays: dict | None, root: int = 0) -> dict:
        """Rank ``root``'s dict of arrays, on every rank (the others pass ``None``)."""
        if self.size == 1:
            return {k: np.array(v) for k, v in (arrays or {}).items()}
        if self.rank == root:
            buf = pack_arrays(arrays or {})
            for r in range(self.size):
                if r != root:
                    self._send_bytes(buf, r, TAG_BCAST)
            return unpack_arrays(buf)
        return unpack_arrays(self._recv_bytes(root, TAG_BCAST))

    def gather(self, record, root: int = 0) -> list | None:
        """Every rank's JSON-able ``record`` as a list in rank order on ``root``, else None."""
        if self.rank != root:
            self._send_bytes(_json_bytes(record), root, TAG_GATHER)
            return None
        out = []
        for r in range(self.size):
            if r == root:
                out.append(json.loads(json.dumps(record)))
            else:
                out.append(_from_json_bytes(self._recv_bytes(r, TAG_GATHER)))
        return out

    def allgather(self, record) -> list:
        """Every rank's JSON-able ``record``, in rank order, on every rank."""
        got = self.gather(record, 0)
        buf = {"json": _json_bytes(got)} if self.rank == 0 else None
        return _from_json_bytes(self.broadcast(buf, 0)["json"])

    def allreduce_max(self, values) -> np.ndarray:
        """Return the element-wise maximum of every rank's float64 ``values`` (same shape)."""
        mine = np.asarray(values, np.float64)
        if self.size == 1:
            return mine.copy()
        if self.rank == 0:
            out = mine.copy()
            for r in range(1, self.size):
                np.maximum(out, unpack_arrays(self._recv_bytes(r, TAG_REDUCE))["v"], out=out)
            return self.broadcast({"v": out}, 0)["v"]
        self._send_bytes(pack_arrays({"v": mine}), 0, TAG_REDUCE)
        return self.broadcast(None, 0)["v"]

    def allreduce_min_max(self, lo: float, hi: float) -> tuple[float, float]:
        """``(min of every rank's lo, max of every rank's hi)`` on every rank."""
        neg_lo, top = self.allreduce_max([-float(lo), float(hi)])
        return -float(neg_lo), float(top)

    def barrier(self) -> None:
        """Wait until every rank got here."""
        self.allreduce_max([0.0])


class SerialCommunicator(Communicator):
    """The only rank (pvpython, a serial pvbatch, the library)."""

    def _send_bytes(self, buffer, dest, tag):  # pragma: no cover - _check_peer refuses first
        raise DVRInputError("a serial run has no other rank")

    _recv_bytes = _send_bytes


class VTKCommunicator(Communicator):
    """ParaView's MPI through a ``vtkMultiProcessController`` (default: the global one)."""

    def __init__(self, controller=None) -> None:
        if controller is None:
            from vtkmodules.vtkParallelCore import vtkMultiProcessController

            controller = vtkMultiProcessController.GetGlobalController()
        if controller is None:
            raise DVRInputError("no vtkMultiProcessController: not running under ParaView/MPI")
        self.controller = controller
        self.rank = int(controller.GetLocalProcessId())
        self.size = int(controller.GetNumberOfProcesses())

    def _send_bytes(self, buffer, dest, tag):
        from vtkmodules.util.numpy_support import numpy_to_vtk

        arr = numpy_to_vtk(np.ascontiguousarray(buffer, np.uint8), deep=True)
        if not self.controller.Send(arr, int(dest), int(tag)):
            raise RuntimeError(f"rank {self.rank}: MPI send to rank {dest} failed")

    def _wait_for(self, source: int, tag: int) -> None:
        """Sleep until a message from ``source`` with ``tag`` is there (``MPI_Iprobe``).

        Open MPI's blocking receive polls the network without pause; with more ranks than
        cores, ranks waiting for their turn then take the cores from the one that works
        (``mpi_yield_when_idle`` only yields them, at full load).  Probing with short sleeps
        (0.05 ms doubling to 2 ms) leaves the cores to the working rank.  Without ``Iprobe``
        (not an MPI communicator) nothing is waited for here.
        """
        probe = getattr(self.controller.GetCommunicator(), "Iprobe", None)
        if probe is None:
            return
        flag, actual = [0], [0]
        pause = 5e-5
        while True:
            if not probe(int(source), int(tag), flag, actual):
                return  # the probe failed: let the blocking receive report it
            if flag[0]:
                return
            time.sleep(pause)
            pause = min(2 * pause, 2e-3)

    def _recv_bytes(self, source, tag):
        from vtkmodules.util.numpy_support import vtk_to_numpy
        from vtkmodules.vtkCommonCore import vtkUnsignedCharArray

        self._wait_for(source, tag)
        arr = vtkUnsignedCharArray()
        if not self.controller.Receive(arr, int(source), int(tag)):
            raise RuntimeError(f"rank {self.rank}: MPI receive from rank {source} failed")
        return vtk_to_numpy(arr).copy() if arr.GetNumberOfTuples() else np.zeros(0, np.uint8)


class _LocalCommunicator(Communicator):
    def __init__(self, rank: int, boxes: dict) -> None:
        self.rank, self.size, self._boxes = rank, int(len(boxes) ** 0.5 + 0.5), boxes

    def _send_bytes(self, buffer, dest, tag):
        self._boxes[(self.rank, dest)].put((tag, np.array(buffer, np.uint8)))

    def _recv_bytes(self, source, tag):
        got_tag, buf = self._boxes[(source, self.rank)].get(timeout=300)
        if got_tag != tag:
            raise RuntimeError(f"rank {self.rank}: expected tag {tag} from {source}, got {got_tag}")
        return buf


def local_group(n: int) -> list[Communicator]:
    """``n`` communicators of this process (one per thread), joined by FIFO queues."""
    boxes = {(a, b): queue.Queue() for a in range(n) for b in range(n)}
    return [_LocalCommunicator(r, boxes) for r in range(n)]


def communicator() -> Communicator:
    """ParaView's MPI ranks (:class:`VTKCommunicator`) when there are several, else serial.

    Examples
    --------
    >>> communicator().size  # no MPI here
    1
    """
    try:
        comm = VTKCommunicator()
    except (DVRInputError, ImportError):
        return SerialCommunicator()
    return comm if comm.size > 1 else SerialCommunicator()


class RankFailure(Exception):
    """What :func:`abort_on_error` reports before it ends the job (tests catch it instead)."""


@contextmanager
def abort_on_error(comm: Communicator, what: str, *, exit=os._exit):
    """End the whole MPI job when the block raises on any rank (one error line, non-zero exit).

    Once the ranks exchange messages, a rank that fails leaves the others waiting for it
    forever.  With several ranks an exception in the block is written as one line
    ``dvr-perception: error: WHAT (rank R): MESSAGE`` on stderr and the process leaves at once
    with status 2 (:class:`~dvr_perception.errors.DVRInputError`) or 1 (anything else):
    ``mpiexec`` then stops every other rank and exits with that status (Open MPI: a rank that
    exits non-zero aborts the job, as ``MPI_Abort`` does).  One rank: the exception propagates.
    ``exit`` is the function that ends the process (tests pass one that raises
    :class:`RankFailure`).

    Examples
    --------
    >>> def leave(status):
    ...     raise RankFailure(status)
    >>> comm = local_group(2)[1]
    >>> try:
    ...     with abort_on_error(comm, "demo", exit=leave):
    ...         raise DVRInputError("bad piece")
    ... except RankFailure as exc:
    ...     print("status", exc.args[0])
    status 2
    """
    try:
        yield
    except BaseException as exc:
        if comm.size < 2 or isinstance(exc, (KeyboardInterrupt, SystemExit, RankFailure)):
            raise
        status = 2 if isinstance(exc, DVRInputError) else 1
        text = " ".join(str(exc).split()) or type(exc).__name__
        if status == 1:
            text = f"{type(exc).__name__}: {text}"
        sys.stdout.flush()
        sys.stderr.write(f"dvr-perception: error: {what} (rank {comm.rank}): {text}\n")
        sys.stderr.flush()
        exit(status)
        raise  # pragma: no cover - ``exit`` returned


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MiB (Linux ``ru_maxrss``).

    Examples
    --------
    >>> peak_rss_mb() > 0
    True
    """
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(kb / (1024.0 * 1024.0) if sys.platform == "darwin" else kb / 1024.0, 1)
