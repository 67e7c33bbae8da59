# SPDX-License-Identifier: Apache-2.0
"""Shared bits of the nodes: latched QoS, clean start and stop, `--help`, Python logging.

- `run_node` / `ros_session`: the first SIGINT or SIGTERM asks the process to stop; the
  second (a terminal's Ctrl-C reaches every process of the group, then `ros2 launch`
  sends its own SIGINT) is ignored while the nodes are destroyed, *before* the context
  is shut down, so no callback or publisher thread meets an invalid context, and a SIGINT
  after the session (a clean-up quicker than launch's signal) is ignored too; a third
  forces the exit, and so does a clean-up still running `CLEANUP_DEADLINE_S` after the
  first or after it began (every thread's stack printed first). Exit code 0 on a signal,
  2 when a node refused its parameters or ROS could not read its arguments (e.g. a
  --params-file; message on stderr), no traceback.
- `node_main`: the entry point of a node executable; `--help` prints the usage and the
  node's parameters from its `Param` table and exits 0 without starting anything; the
  process leaves without interpreter finalization once its nodes are destroyed;
  SIGUSR1 (`STACKS_SIGNAL`) prints every thread's stack and the node goes on.
- `forward_python_logging`: records of the core's Python loggers (`ae_tactile.*`, e.g. the
  serial link's warnings) go to the node's rclpy logger, hence to the console and /rosout.
"""
from __future__ import annotations

import faulthandler
import importlib
import logging
import logging.handlers
import os
import queue
import signal
import socket
import sys
import threading
from contextlib import ExitStack, contextmanager

import rclpy
import rclpy.logging
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from ae_tactile.ros import params as shared_params
from ae_tactile.ros.cpus import (  # noqa: F401  (public here too)
    cpu_list,
    cpu_list_problem,
    hand_topic_problem,
    pin_process,
)
from ae_tactile.ros.exit_timer import start_exit_timer
from ae_tactile.ros.node_help import (  # noqa: F401  (public here too)
    format_usage,
    module_params,
    print_help,
    split_ros_args,
    wants_help,
)
from ae_tactile.ros.params import ParameterError

#: Latched topics (sensor_info, contact_state, sim/port): reliable, transient local, depth 1.
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)

#: A clean-up still running this long after the first SIGINT/SIGTERM, or after it began
#: (s), prints every thread's stack to stderr (the launch log: where it hangs) and the
#: process leaves without finishing it (exit code as if it had: 0 on a stop signal). A
#: clean-up takes milliseconds; what can hang is the middleware's teardown, which must
#: not keep a stopped node alive until someone sends SIGKILL.
CLEANUP_DEADLINE_S = 20.0
#: The line the forced exit prints on stderr (after the stacks).
CLEANUP_FORCED_EXIT_TEXT = "[ae_tactile] the clean-up did not end in time"

#: Longest time the spin loop blocks before it looks at the stop request (s). A Python
#: signal handler only runs between bytecodes, never inside rcl_wait.
STOP_POLL_S = 0.1

_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: The signal that forces an immediate exit: a terminal's Ctrl-C and `ros2 launch` each
#: send one SIGINT (ignored while cleaning up); a third (launch's SIGTERM after its
#: timeout, or Ctrl-C pressed again) means the clean-up hangs.
FORCE_EXIT_SIGNALS = 3


def _start_cleanup_deadline(state: dict, done: threading.Event):
    """Bound the clean-up that the first stop signal starts: unless ``done`` is set within
    `CLEANUP_DEADLINE_S`, a daemon thread prints every thread's stack (to file descriptor
    2, whatever ``sys.stderr`` is) and ends the process with the stop's exit code. Should
    the main thread take the GIL for good meanwhile (stuck inside a call that never
    releases it), no Python thread runs again: faulthandler's own C thread prints the
    stacks 2 s later and a C timer (`exit_timer`) ends the process with the same exit
    code 0.5 s after that (where no such timer can be made: faulthandler ends it, exit
    code 1). Returns that timer (None without one), to be cancelled with the deadline."""
    deadline_s = float(CLEANUP_DEADLINE_S)
    stuck_s = deadline_s + 2.0  # [s] after the Python thread's own chance, which prints more
    exit_timer = start_exit_timer(stuck_s + 0.5, int(state.get("exit", 0)))
    try:
        faulthandler.dump_traceback_later(stuck_s, exit=exit_timer is None, file=2)
    except (OSError, ValueError, RuntimeError):
        pass                                   # the deadline thread below still works

    def leave_if_stuck():
        if done.wait(deadline_s):
            return
        try:
            faulthandler.dump_traceback(file=2, all_threads=True)
        except (OSError, ValueError, RuntimeError):
            pass
        os.write(2, (f"{CLEANUP_FORCED_EXIT_TEXT} ({deadline_s:g} s; each thread's stack "
                     "above): leaving without it\n").encode())
        os._exit(int(state.get("exit", 0)))

    threading.Thread(target=leave_if_stuck, name="ae_tactile_cleanup_deadline",
                     daemon=True).start()
    return exit_timer


# ------------------------------------------------------------------ start and stop
def _signal_watcher(stop: threading.Event, arm_cleanup_deadline):
    """The thread body that counts the stop signals written to its socket (by
    `signal.set_wakeup_fd`): records the stop, arms the clean-up deadline, and forces the
    exit on the FORCE_EXIT_SIGNALS-th signal."""

    def watch_signals(sock):
        count = 0
        while True:
            try:
                data = sock.recv(64)
            except OSError:
                return
            if not data:           # the session is over (the other end was closed)
                return
            count += sum(1 for b in data if b in _STOP_SIGNALS)
            if not count:
                continue
            stop.set()
            arm_cleanup_deadline()
            if count >= FORCE_EXIT_SIGNALS:   # the clean-up hangs: the user insists
                os.write(2, b"[ae_tactile] clean-up interrupted again: forced exit\n")
                os._exit(1)

    return watch_signals


def _quiet_unraisable(stop: threading.Event, previous_hook):
    """An unraisable hook that drops the stop signal's KeyboardInterrupt.

    That KeyboardInterrupt, when the signal lands while C code calls back into Python
    (a ctypes callback, e.g. llvmlite's while numba loads or compiles kernels at start-up):
    Python cannot raise it there and would print it as "Exception ignored" with a
    traceback. The stop is already recorded in state['stop'] (the start-up goes on and the
    node exits without spinning): nothing to report."""

    def unraisable(info):
        if info.exc_type is KeyboardInterrupt and stop.is_set():
            return
        previous_hook(info)

    return unraisable


class _CleanupDeadline:
    """The clean-up deadline, armed once (from the watcher on the first stop signal, and
    from the main thread where its clean-up begins: the watcher needs the GIL, which a main
    thread stuck inside a call may never free), closed at the end."""

    def __init__(self, state: dict):
        self.state = state
        self.done = threading.Event()
        self.lock = threading.Lock()
        self.started = False
        self.closed = False
        self.exit_timer = None

    def arm(self) -> None:
        with self.lock:
            if not self.started and not self.closed:
                self.started = True
                self.exit_timer = _start_cleanup_deadline(self.state, self.done)

    def close(self) -> None:
        with self.lock:
            self.closed = True
            started = self.started
        self.done.set()
        if started:            # (a timer armed by someone else, e.g. pytest's, stays)
            faulthandler.cancel_dump_traceback_later()
            if self.exit_timer is not None:
                self.exit_timer.cancel()


def _start_watcher(undo: ExitStack, watch_signals) -> socket.socket:
    """The watcher thread on a socket pair; returns the end `signal.set_wakeup_fd` writes
    to. Undone: its peer closes, it reads the end of the stream and returns, then its own
    socket closes (not under a thread still reading it)."""
    wake_read, wake_write = socket.socketpair()
    watcher = threading.Thread(target=watch_signals, args=(wake_read,),
                               name="ae_tactile_stop_signals", daemon=True)

    @undo.callback
    def _close_read():
        if not watcher.is_alive():
            wake_read.close()

    undo.callback(lambda: watcher.is_alive() and watcher.join(1.0))
    undo.callback(wake_write.close)
    wake_write.setblocking(False)
    watcher.start()
    return wake_write


@contextmanager
def _stop_on_signals(state: dict):
    """Route SIGINT/SIGTERM to ``state['stop']``; while ``state['interrupt']`` is true the
    first one also raises KeyboardInterrupt in the main thread (to abort a long start-up,
    or for loops that do not poll the event). The second is ignored, the third forces
    the exit, and so does a clean-up still running `CLEANUP_DEADLINE_S` after the first.

    Python runs a signal handler in the main thread only, between bytecodes: a main thread
    stuck inside a call would never see the signal. So the signals are also counted by a
    thread of their own, woken through `signal.set_wakeup_fd` (Python's C-level handler
    writes each signal's number there, whatever the main thread does): it records the
    stop, starts the clean-up deadline and forces the exit on the third signal."""
    if threading.current_thread() is not threading.main_thread():
        yield                      # signals are delivered to the main thread only
        return
    stop = state["stop"]
    deadline = _CleanupDeadline(state)
    interrupted = [False]          # the handler raised its one KeyboardInterrupt
    signalled = [False]            # a stop signal came: the process is leaving

    def handler(signum, frame):
        # (not 'the first signal': the watcher below may have set the event already)
        signalled[0] = True
        stop.set()
        if state["interrupt"] and not interrupted[0]:
            interrupted[0] = True
            raise KeyboardInterrupt

    state["arm_cleanup_deadline"] = deadline.arm
    previous_hook = sys.unraisablehook
    # Each step is undone at the end (last first), also when a later step fails.
    with ExitStack() as undo:
        wake_write = _start_watcher(undo, _signal_watcher(stop, deadline.arm))
        previous_wakeup = signal.set_wakeup_fd(wake_write.fileno(), warn_on_full_buffer=False)
        undo.callback(signal.set_wakeup_fd, previous_wakeup)
        for sig in _STOP_SIGNALS:
            undo.callback(_after_session, sig, signal.signal(sig, handler), signalled)
        sys.unraisablehook = _quiet_unraisable(stop, previous_hook)
        undo.callback(setattr, sys, "unraisablehook", previous_hook)
        undo.callback(deadline.close)
        yield


def _after_session(sig, previous, signalled) -> None:
    """At the end of a session, ``sig``'s handler from before it; SIGINT ignored instead
    once a stop signal came (``signalled[0]``): a terminal's Ctrl-C reaches every process
    of the group and `ros2 launch` sends its own SIGINT, and one arriving after a quick
    clean-up, while the process leaves, would end it by the signal (exit code -2)."""
    stopping = signalled[0] and sig == signal.SIGINT
    signal.signal(sig, signal.SIG_IGN if stopping else previous)


def _nothing() -> None:
    """(no clean-up deadline outside the main thread: no signals there)"""


def _from_stop_signal(exc: BaseException, stop: threading.Event) -> bool:
    """Whether ``exc`` is the stop signal's KeyboardInterrupt under another name: raised
    where Python wraps it (Python 3.11 turns an exception inside a class body's
    ``__set_name__``, e.g. while a module is imported, into a RuntimeError caused by it)."""
    seen = 0
    while exc is not None and seen < 8:
        if isinstance(exc, KeyboardInterrupt):
            return stop.is_set()
        exc, seen = exc.__cause__, seen + 1   # wrapped: 'the direct cause'
    return False


@contextmanager
def ros_session(args=None, interrupt: bool = True):
    """rclpy.init ... try_shutdown around a node's life; yields a dict with 'exit' (the
    process exit code: 2 when a node refused its parameters, else 0), 'stop' (a
    threading.Event set by the first SIGINT/SIGTERM), 'interrupt' (whether that first
    signal also raises KeyboardInterrupt in the body; the body may change it) and
    'arm_cleanup_deadline' (the body calls it where its clean-up begins).

    rclpy's own signal handlers are not installed: they shut the context down from the
    signal, while node threads may still publish ("context is not valid"). Here a signal
    only requests the stop; the body destroys its nodes and the context goes last; a
    second signal is ignored, so the clean-up is not interrupted (a third forces the exit).
    """
    state = {"exit": 0, "stop": threading.Event(), "interrupt": interrupt,
             "arm_cleanup_deadline": _nothing}
    with _stop_on_signals(state):
        try:
            rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        except Exception as exc:   # RCLError: unreadable --params-file, bad --ros-args
            print(f"[ae_tactile] not starting: {exc}", file=sys.stderr, flush=True)
            raise SystemExit(2) from None
        try:
            yield state
        except ParameterError as exc:
            print(f"[ae_tactile] not starting: {exc}", file=sys.stderr, flush=True)
            state["exit"] = 2
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except Exception as exc:
            if not _from_stop_signal(exc, state["stop"]):
                raise
        finally:
            state["interrupt"] = False
            state["arm_cleanup_deadline"]()
            rclpy.try_shutdown()


def spin_until_stopped(executor, stop: threading.Event) -> None:
    """Spin ``executor`` until ``stop`` is set or the context is shut down elsewhere."""
    context = executor.context
    while not stop.is_set() and context.ok():
        executor.spin_once(timeout_sec=STOP_POLL_S)


class _ProcessLog:
    """Stands in for a node in `forward_python_logging`: an rclpy logger of its own."""

    def __init__(self, name: str):
        self._logger = rclpy.logging.get_logger(name)

    def get_logger(self):
        return self._logger


def run_node(node_factory, args=None, executor_factory=SingleThreadedExecutor,
             many: bool = False) -> int:
    """Create one node, spin it until SIGINT/SIGTERM/shutdown and destroy it while the
    context is still valid. Returns the exit code: 0, or 2 on a parameter error.

    With ``many``, ``node_factory(nodes)`` appends each node it makes to the list
    ``nodes`` as soon as it exists (so that those made before a failing one are destroyed
    too) and they spin in one executor.

    A signal during the node's construction (which may JIT-compile for a while) aborts
    the construction; during spinning it ends the loop within STOP_POLL_S. ``-h`` or
    ``--help`` before ``--ros-args`` (``python -m ae_tactile.ros.<node> --help``) prints
    the usage of the factory's module (`print_help`) and returns 0 without starting ROS.
    Parameter names given to the node that it does not have are warned about once
    (`params.warn_unknown_parameters`) unless the node did so itself."""
    own, _ = split_ros_args(sys.argv[1:] if args is None else list(args))
    if wants_help(own):
        module = sys.modules[node_factory.__module__]
        executable = getattr(module, "EXECUTABLE", None) or os.path.basename(
            sys.argv[0]
        ).removesuffix(".py")
        print_help(module, executable)
        return 0
    nodes: list = []

    def log_to():
        """The node whose logger gets the core's records; with several, the process's
        own logger (named after the executable): no one node speaks for the others."""
        if not nodes:
            return None
        return _ProcessLog(os.path.basename(sys.argv[0]) or "ae_tactile") if many else nodes[0]

    with ros_session(args, interrupt=True) as state, forward_python_logging(log_to):
        try:
            if many:
                node_factory(nodes)
            else:
                nodes.append(node_factory())
            state["interrupt"] = False
            for node in nodes:
                if not getattr(node, "_ae_tactile_names_checked", False):
                    shared_params.warn_unknown_parameters(node)  # a misspelt -p is not silent
            if not state["stop"].is_set():
                executor = executor_factory()
                for node in nodes:
                    executor.add_node(node)
                try:
                    spin_until_stopped(executor, state["stop"])
                finally:
                    executor.shutdown(timeout_sec=1.0)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except Exception as exc:
            if not _from_stop_signal(exc, state["stop"]):
                raise
        finally:
            state["interrupt"] = False
            state["arm_cleanup_deadline"]()
            for node in reversed(nodes):
                node.destroy_node()
    return state["exit"]


def events_executor():
    """rclpy's events executor where available (far less work per timer wake-up, which the
    reader thread would otherwise wait for), else the single-threaded one."""
    try:
        from rclpy.experimental import EventsExecutor  # lazy: optional (newer rclpy only)

        return EventsExecutor()
    except ImportError:
        return SingleThreadedExecutor()


def exit_process(code: int) -> None:
    """Flush and leave at once, skipping interpreter finalization: native threads of DDS
    and JIT code (daemon threads frozen mid-call) can deadlock the final garbage
    collection, which would hang a node's exit after a clean shutdown."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


# ------------------------------------------------------------------ Python logging
class RosLogHandler(logging.Handler):
    """logging.Handler that re-emits records through an rclpy logger.

    ``get_ros_logger()`` returns the rclpy logger to use (the node's, so records reach
    /rosout) or None (then an rclpy logger named ``fallback_name``: console only, for
    records logged while the node is being constructed).
    """

    def __init__(self, get_ros_logger, fallback_name: str = "ae_tactile"):
        super().__init__(logging.DEBUG)
        self._get_ros_logger = get_ros_logger
        self._fallback = rclpy.logging.get_logger(fallback_name)
        self.setFormatter(logging.Formatter("[%(name)s] %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            logger = self._get_ros_logger() or self._fallback
            msg = self.format(record)
            # rclpy keys each call site to one severity: one call per level.
            if record.levelno >= logging.ERROR:
                logger.error(msg)
            elif record.levelno >= logging.WARNING:
                logger.warning(msg)
            elif record.levelno >= logging.INFO:
                logger.info(msg)
            else:
                logger.debug(msg)
        except Exception:   # a logging failure must never take the node down
            self.handleError(record)


@contextmanager
def forward_python_logging(get_node, logger_name: str = "ae_tactile", level=logging.INFO):
    """While active, records of ``logger_name`` and its children go to the rclpy logger
    of ``get_node()`` (None while the node does not exist yet) instead of stderr.

    The thread that logs only queues the record; a thread of its own hands it to rclpy
    (`logging.handlers.QueueListener`). rclpy's logger looks up its caller's source file
    on every call (~0.2 ms, and tens of ms on the first call after many imports): that
    must not stall the link's reader when a device sends garbage. Records still queued
    when the context ends are handed over before it returns. Yields the `RosLogHandler`."""
    def ros_logger():
        node = get_node()
        return node.get_logger() if node is not None else None

    handler = RosLogHandler(ros_logger)
    records: queue.SimpleQueue = queue.SimpleQueue()
    listener = logging.handlers.QueueListener(records, handler, respect_handler_level=True)
    queued = logging.handlers.QueueHandler(records)
    py_logger = logging.getLogger(logger_name)
    saved = (py_logger.level, py_logger.propagate)
    listener.start()
    py_logger.addHandler(queued)
    py_logger.setLevel(level)
    py_logger.propagate = False
    try:
        yield handler
    finally:
        py_logger.removeHandler(queued)
        py_logger.setLevel(saved[0])
        py_logger.propagate = saved[1]
        listener.stop()  # hands over what is still queued


# ------------------------------------------------------------------ entry points
#: `kill -USR1 <pid>` makes a node print every thread's Python stack on stderr (its launch
#: log) and go on: where a node hangs, even while one thread holds the GIL for good.
STACKS_SIGNAL = signal.SIGUSR1


def print_stacks_on_signal(signum: int = STACKS_SIGNAL) -> bool:
    """Register faulthandler on ``signum`` (its C handler needs no GIL), and on the fatal
    signals (SIGSEGV, SIGBUS, SIGFPE, SIGABRT, SIGILL: a crash in compiled code prints every
    thread's Python stack on stderr, the launch log, before the process dies as it would);
    False where the platform cannot (the node still runs)."""
    try:
        faulthandler.enable(file=2, all_threads=True)
        faulthandler.register(signum, file=2, all_threads=True, chain=False)
        return True
    except (AttributeError, OSError, ValueError, RuntimeError):
        return False


def node_main(module_name: str, tables=None, argv=None) -> int:
    """Entry point of a node executable; ``tables``: (prefix, source) pairs of the node's
    parameters for ``--help`` (see `module_params`).

    ``-h``/``--help`` (before ``--ros-args``) prints the usage with every parameter of the
    node and returns 0 without initialising ROS; any other non-ROS argument is refused
    with exit code 2; otherwise ``module.main()`` runs the node.
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    print_stacks_on_signal()
    executable = os.path.basename(sys.argv[0]) or module_name
    own, _ = split_ros_args(argv)
    module = importlib.import_module(module_name)
    if wants_help(own):
        print_help(module, executable, tables)
        return 0
    if own:
        print(f"{executable}: unrecognized arguments: {' '.join(own)}\n"
              f"(parameters go after --ros-args: -p NAME:=VALUE; see {executable} --help)",
              file=sys.stderr)
        return 2
    exit_process(module.main())
