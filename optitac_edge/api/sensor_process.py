"""A sensor read in a process of its own (:func:`open_sensor_process`), so that the threads of the program that
reads it (a LeRobot recorder encoding video, a policy) cannot hold the sensor's frames back.

The child is ``python -c CHILD FD``: it opens the sensor with :func:`open_sensor` (the
same pipeline, nothing copied) and answers each call of the parent's :class:`SensorProcess` over a socket pair
(:class:`multiprocessing.connection.Connection` framing, :mod:`~optitac_edge.api.sensor_messages`' data: one
call, one answer; nothing pickled). The parent keeps no thread: a
reading crosses the socket only when it is asked for. The child ends when it is told to, and by itself when its
end of the socket reads end-of-file (the parent closed it, or died).
"""

from __future__ import annotations

import logging
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Mapping
from multiprocessing.connection import Connection
from types import TracebackType
from typing import TYPE_CHECKING, Any, cast

from optitac_edge.api import sensor_messages as messages
from optitac_edge.api.readings import Reading, Status
from optitac_edge.api.sensor import Sensor, check_open_arguments, iter_readings, open_sensor
from optitac_edge.errors import OptiTacError
from optitac_edge.io.threads import NamedThread

if TYPE_CHECKING:
    from typing_extensions import Self

log = logging.getLogger(__name__)

#: The calls the child answers: :class:`Sensor` methods, each with positional arguments only.
CALLS = frozenset({"read", "start", "latest", "stop", "tare", "status"})
#: The child's program: :func:`main` of this module on the socket's descriptor (not ``-m``: this module is
#: imported already by the package, and ``runpy`` would run a second copy of it).
CHILD = "import sys; from optitac_edge.api.sensor_process import main; sys.exit(main(sys.argv[1:]))"
#: How much longer than the call's own wait the parent waits for an answer before it ends the child, s.
ANSWER_MARGIN_S = 10.0
#: The longest the parent waits for the child to open its sensor (import, camera, a fiber map from rest), s.
OPEN_TIMEOUT_S = 120.0


class SensorProcess:
    """One sensor of a board, open in a child process. Use :func:`open_sensor_process`.

    The methods of :class:`Sensor` (:meth:`read`, :meth:`readings`, :meth:`start`, :meth:`latest`,
    :meth:`stop`, :meth:`tare`, :meth:`status`, :meth:`close`), with the same arguments, results and errors;
    each is one call to the child and its answer (a reading with ``arrays`` is ~41 KB: ~0.6 ms a
    :meth:`latest` here).
    Read in the background (:meth:`start`), the child's thread reads every frame at the camera's rate whatever
    this process does; :meth:`latest` fetches the newest.

    Every call is numbered and takes only the answer with its number: the answer of a call interrupted while
    it waited (Ctrl-C caught by the program) is dropped when it comes; a call interrupted while its message or
    its answer was half across ends the child (the stream cannot be trusted), and the next call says so.
    Calls from several threads take turns (one lock).
    """

    def __init__(self, process: subprocess.Popen[bytes], conn: Connection, sensor_id: int, name: str,
                 camera_timeout_s: float) -> None:
        self._process, self._conn = process, conn
        self._closed = False
        #: Held for a whole call and its answer: a second thread's call waits its turn.
        self._lock = threading.Lock()
        #: The number of the last call sent (the open was 0).
        self._number = 0
        #: Why the connection was ended under a call (an interrupted message), for the next call's line.
        self._ended_why = ""
        self._camera_timeout_s = camera_timeout_s
        #: The board config's id of this sensor (what the MCU hears).
        self.sensor_id = sensor_id
        #: Its name in the board config.
        self.name = name

    @property
    def pid(self) -> int:
        """The child's process id."""
        return self._process.pid

    def _call(self, method: str, *args: object, wait_s: float = 0.0) -> object:
        """``method(*args)`` in the child; its result, or its error raised here."""
        with self._lock:
            return self._locked_call(method, args, wait_s)

    def _locked_call(self, method: str, args: tuple[object, ...], wait_s: float) -> object:
        if self._closed:
            raise OptiTacError(f"sensor {self.sensor_id} {self.name!r} is closed{self._ended_why}")
        limit = wait_s + self._camera_timeout_s + ANSWER_MARGIN_S
        number = self._number + 1
        message = messages.encode({"call": method, "args": list(args), "id": number}, f"{method}()")  # not sent
        self._number = number
        phase = "sending"
        try:
            self._conn.send_bytes(message)
            phase = "waiting"
            deadline = time.monotonic() + limit
            while self._conn.poll(max(deadline - time.monotonic(), 0.0)):
                phase = "receiving"
                answered, value = messages.recv_reply(self._conn)
                phase = "waiting"
                if answered == number:
                    if isinstance(value, OptiTacError):
                        raise value
                    return value
                if not 0 < answered < number:
                    raise messages.MalformedMessage(f"sensor process: an answer to call {answered}, "
                                                    f"the last call was {number}")
                # an answer to an earlier call that was interrupted while it waited: not this call's
        except (EOFError, OSError) as exc:
            self._end()
            raise OptiTacError(f"sensor {self.sensor_id} {self.name!r}: its process ended "
                               f"(exit status {self._process.poll()}): {type(exc).__name__}") from None
        except messages.MalformedMessage:
            self._end()
            raise
        except BaseException:  # KeyboardInterrupt, SystemExit, a signal handler's exception
            if phase != "waiting":  # half a message across: the stream cannot be trusted
                self._ended_why = f" (ended when {method}() was interrupted while {phase} a message)"
                self._end()
            raise
        self._end()
        raise OptiTacError(f"sensor {self.sensor_id} {self.name!r}: its process did not answer {method}() within "
                           f"{limit:.1f} s; it was ended")

    def read(self, timeout_s: float = 1.0) -> Reading | None:
        """:meth:`Sensor.read` in the child."""
        return cast("Reading | None", self._call("read", timeout_s, wait_s=_wait(timeout_s)))

    def readings(self, duration_s: float | None = None, timeout_s: float = 1.0) -> Iterator[Reading]:
        """:meth:`Sensor.readings`: every frame's reading, for ``duration_s`` of frame time."""
        return iter_readings(self.read, duration_s, timeout_s)

    def __iter__(self) -> Iterator[Reading]:
        return self.readings()

    def start(self) -> None:
        """:meth:`Sensor.start`: the child reads every frame in a thread of its own."""
        self._call("start")

    def latest(self, timeout_s: float = 0.0) -> Reading | None:
        """:meth:`Sensor.latest`: the newest reading not returned before."""
        return cast("Reading | None", self._call("latest", timeout_s, wait_s=_wait(timeout_s)))

    def stop(self) -> None:
        """:meth:`Sensor.stop` in the child."""
        self._call("stop")

    def tare(self, wait_s: float | None = None) -> bool:
        """:meth:`Sensor.tare` in the child."""
        return bool(self._call("tare", wait_s, wait_s=_wait(wait_s or 0.0)))

    def status(self) -> Status:
        """:meth:`Sensor.status` of the child's sensor."""
        return cast("Status", self._call("status"))

    def close(self) -> None:
        """Close the sensor and end the child, waiting for it (idempotent)."""
        with self._lock:
            if self._closed:
                return
            try:
                self._locked_call("close", (), 0.0)
            except OptiTacError:  # the child ended already, or did not answer: ended all the same
                pass
            finally:
                self._end()

    def _end(self) -> None:
        """Close the socket and wait for the child (:func:`_reap`)."""
        self._closed = True
        self._conn.close()
        _reap(self._process)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def _portable_path(value: object) -> object:
    """A path-like value as its string (what the child opens); anything else as it is."""
    return os.fspath(value) if isinstance(value, os.PathLike) else value


def _wait(seconds: object) -> float:
    """How long a call may wait by its own argument (the child checks the argument itself)."""
    return float(seconds) if isinstance(seconds, (int, float)) and not isinstance(seconds, bool) \
        and 0 <= seconds < 1e6 else 0.0


def open_sensor_process(board: str | os.PathLike[str] = "sim", *, sensor: int | None = None,
                        cal: str | os.PathLike[str] | None = None, recording: str | os.PathLike[str] | None = None,
                        settings: Mapping[str, Any] | None = None, arrays: bool = False) -> SensorProcess:
    """Open one sensor of a board in a process of its own: :func:`open_sensor`'s arguments, a
    :class:`SensorProcess` with :class:`Sensor`'s methods.

    Raises
    ------
    OptiTacError
        What :func:`open_sensor` raises, from the child; or the child could not start or did not open the
        sensor within 120 s.
    """
    check_open_arguments(board, sensor, settings, cal, recording)
    options = {"sensor": sensor, "cal": _portable_path(cal), "recording": _portable_path(recording),
               "settings": None if settings is None else dict(settings), "arrays": bool(arrays)}
    message = messages.encode({"open": os.fspath(board), "options": options}, "open_sensor_process")
    mine, theirs = socket.socketpair()
    try:
        process = subprocess.Popen([sys.executable, "-c", CHILD, str(theirs.fileno())], pass_fds=(theirs.fileno(),),
                                   stdin=subprocess.DEVNULL)
    except OSError as exc:
        mine.close()
        raise OptiTacError(f"the sensor process could not start: {exc}") from None
    finally:
        theirs.close()
    conn = Connection(mine.detach())
    try:
        conn.send_bytes(message)
        if not conn.poll(OPEN_TIMEOUT_S):
            raise OptiTacError(f"the sensor process did not open board {board} within {OPEN_TIMEOUT_S:.0f} s")
        opened = messages.recv_answer(conn)
    except (EOFError, OSError):
        conn.close()
        process.wait()
        raise OptiTacError(f"the sensor process ended while opening board {board} "
                           f"(exit status {process.returncode})") from None
    except OptiTacError:  # the child's open_sensor refused (it ends by itself), or no answer
        conn.close()
        _reap(process)
        raise
    except BaseException:
        conn.close()
        process.kill()
        process.wait()
        raise
    sensor_id, name, camera_timeout_s = cast("tuple[int, str, float]", opened)
    return SensorProcess(process, conn, sensor_id, name, camera_timeout_s)


def _reap(process: subprocess.Popen[bytes]) -> None:
    """Wait up to :data:`ANSWER_MARGIN_S` for a child to end by itself, then end it."""
    try:
        process.wait(ANSWER_MARGIN_S)
    except subprocess.TimeoutExpired:
        log.warning("sensor process %d did not end: killed", process.pid)
        process.kill()
        process.wait()


def serve(conn: Connection) -> None:
    """The child: open the sensor the first message names, then answer calls until ``close`` or end-of-file."""
    try:
        first = messages.decode(messages.receive(conn))
        if not isinstance(first.get("options"), dict):
            raise messages.MalformedMessage("sensor process: the first message is not an open")
        with ParentWatch(conn):  # a parent that dies meanwhile ends this process at once
            opened: Sensor = open_sensor(first.get("open"), **first["options"])  # type: ignore[arg-type]
    except (EOFError, OSError):
        return
    except Exception as exc:  # noqa: BLE001  (handed to the parent, which raises it)
        _answer(conn, exc, 0)
        return
    with opened:
        if not _answer(conn, (opened.sensor_id, opened.name, opened.camera_timeout_s), 0):
            return
        while _serve_call(conn, opened):
            pass


def _answer(conn: Connection, value: object, number: int) -> bool:
    """Send an answer; False when the parent is gone (it closed its end, or died: nothing to say to it)."""
    try:
        messages.send_answer(conn, value, number)
    except OSError:
        return False
    return True


def _serve_call(conn: Connection, opened: Sensor) -> bool:
    """Answer one call; False when the child is done (``close``, or the parent is gone)."""
    try:
        call = messages.decode(messages.receive(conn))
        number = messages.call_id(call)
    except (EOFError, OSError):
        return False  # the parent closed its end, or died
    except messages.MalformedMessage as exc:  # the stream cannot be trusted: said, then ended
        _answer(conn, exc, 0)
        return False
    method, args = call.get("call"), call.get("args")
    if method == "close":
        opened.close()
        _answer(conn, None, number)
        return False
    if method not in CALLS or not isinstance(args, list):
        return _answer(conn, OptiTacError(f"the sensor process has no call {method!r}"), number)
    try:
        answer: object = getattr(opened, method)(*args)
    except Exception as exc:
        log.debug("sensor process: %s failed", method, exc_info=exc)
        answer = exc
    return _answer(conn, answer, number)


class ParentWatch:
    """While the child opens its sensor (seconds: imports, a camera, a fiber map), a thread watches the socket:
    end-of-file there (the parent closed it, or died) ends the child at once. A call arriving ends the watch;
    the call stays in the socket for the child to read."""

    def __init__(self, conn: Connection, poll_s: float = 0.1) -> None:
        self._conn, self._poll_s = conn, poll_s
        self._done = threading.Event()
        self._thread = NamedThread(target=self._watch, name="optitac-parent", daemon=True)

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        self._thread.join()

    def _watch(self) -> None:
        peer = socket.socket(fileno=os.dup(self._conn.fileno()))
        try:
            while not self._done.is_set():
                readable, _, _ = select.select([peer], [], [], self._poll_s)
                if not readable:
                    continue
                try:
                    data = peer.recv(1, socket.MSG_PEEK)
                except OSError:
                    data = b""
                if not data:  # end-of-file: nobody will read what this process opens
                    os._exit(0)
                return  # a call: the parent is there
        finally:
            peer.close()


def main(argv: list[str]) -> int:
    """The child's program (:data:`CHILD`): serve the socket inherited as descriptor ``argv[0]``."""
    if len(argv) != 1 or not argv[0].isdigit():
        sys.stderr.write("the sensor process takes one argument, its socket's descriptor "
                         "(it is started by open_sensor_process)\n")
        return 2
    # Ctrl-C at a terminal reaches the whole process group: the parent decides, and the child ends when the
    # parent closes it or its end of the socket closes (no traceback of an interrupted wait here)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    conn = Connection(int(argv[0]))
    try:
        serve(conn)
    finally:
        conn.close()
    return 0
