"""The ``o3d-mvps`` command line: one program, one module per subcommand.

Each subcommand module has ``register(subparsers)`` adding its parser with
``set_defaults(handler=run)``, and ``run(args) -> int``. Exit codes: 0 ok, 1 failure (the
message names the fix), 2 usage, 130 interrupted (Ctrl-C or SIGTERM, at any moment: one line
on stderr, and the process ends within :data:`STOP_SECONDS`).
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import threading

from ..errors import MVPSError

SUBCOMMANDS = ["demo", "render", "refine", "reconstruct", "export", "record"]
QUIET_HELP = ("no progress bars, intermediate logs, warnings (still listed in report.json) or Open3D and Dask "
              "messages; the final 'wrote ...' lines are still printed")
INTERRUPTED = 130  # 128 + SIGINT, the shell's code for a command stopped by Ctrl-C
#: Seconds an interrupted command has to clean up (remove its staging folders, close its Dask
#: cluster) before it is ended anyway, with the same line and exit code.
STOP_SECONDS = 0.5

_said = threading.Lock()  # held once the "interrupted" line is printed: it is printed once
_received: list = []  # the signals received (the first one counts)


def interrupted() -> bool:
    """Whether SIGINT or SIGTERM has arrived since :func:`stop_on_signals` (an exception raised
    then is the interrupt's, whatever its type: e.g. Open3D's import turns it into ImportError)."""
    return bool(_received)


_prog = ["o3d-mvps"]  # the running command's name, for the line a signal prints


#: Environment of a command run under :func:`supervise`: the file descriptor it writes a byte to
#: once it has printed its "interrupted" line (so the supervisor does not print a second one).
SAID_FD = "O3D_MVPS_SAID_FD"


def _say_interrupted(prog: str | None = None) -> None:
    """Print ``PROG: interrupted`` on stderr, once per process (and tell a supervisor)."""
    if _said.acquire(blocking=False):
        # a progress bar mid-line: the line starts on a line of its own
        bars = "tqdm" in sys.modules and bool(getattr(sys.modules["tqdm"].tqdm, "_instances", None))
        print(f"{chr(10) if bars else ''}{prog or _prog[0]}: interrupted", file=sys.stderr, flush=True)
        if os.environ.get(SAID_FD):
            try:
                os.write(int(os.environ[SAID_FD]), b"1")
            except (OSError, ValueError):
                pass


def _silence_stderr() -> None:
    """Send what the process writes to stderr from now on (the tracebacks and log lines of
    threads and libraries torn down by an interrupt) to the null device."""
    try:
        sys.stderr.flush()
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, 2)
        os.close(null)
    except OSError:
        pass


def _end_now(prog: str | None = None) -> None:
    """The watchdog's end of an interrupted command whose cleanup takes too long: the line, the
    multiprocessing semaphores unlinked and child processes stopped (no leak warnings), exit 130."""
    _say_interrupted(prog)
    try:
        import multiprocessing
        from multiprocessing import util

        for child in multiprocessing.active_children():
            child.kill()
        util._run_finalizers(0)  # unlinks the named semaphores, as a normal exit does
    except Exception:  # noqa: BLE001 - ending anyway
        pass
    sys.stderr.flush()
    os._exit(INTERRUPTED)


def stop_on_signals(prog: str) -> dict | None:
    """Make SIGINT (Ctrl-C) and SIGTERM raise KeyboardInterrupt in the main thread, so that the
    command cleans up as it unwinds; the first signal also starts a watchdog that ends the process
    with exit code 130 after :data:`STOP_SECONDS` if it is still running. Later signals are ignored
    (the watchdog is already counting). Returns the handlers replaced (None off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    _received.clear()
    _prog[0] = prog
    if _said.locked():  # a new command (main called again in one process) says it anew
        _said.release()

    def interrupt(signum, frame):
        if _received:
            return
        _received.append(signum)
        _say_interrupted()
        _silence_stderr()
        threading.Thread(target=lambda: (threading.Event().wait(STOP_SECONDS), _end_now()), daemon=True,
                         name="o3d_mvps-stop").start()
        raise KeyboardInterrupt

    return {sig: signal.signal(sig, interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}


def restore_signals(previous: dict | None) -> None:
    """Put back the handlers :func:`stop_on_signals` replaced (for callers of ``main`` in-process)."""
    for sig, handler in (previous or {}).items():
        signal.signal(sig, handler)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="o3d-mvps",
        description="Depth super-resolution and multi-view photometric stereo for an LED-lit RGB-D camera.",
        epilog="exit codes: 0 ok, 1 failure (the message names the fix), 2 usage, 130 interrupted (Ctrl-C)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMANDS:
        importlib.import_module(f"{__name__}.{name}").register(sub)
    for subparser in sub.choices.values():  # --quiet after the subcommand too; SUPPRESS keeps one given before
        subparser.add_argument("--quiet", action="store_true", default=argparse.SUPPRESS, help=QUIET_HELP)
    return parser


def run_handler(prog: str, run, args) -> int:
    """``run(args)``'s exit code; a failure prints ``PROG: error: message`` and gives 1, Ctrl-C
    prints ``PROG: interrupted`` and gives 130 (outputs are written all or nothing, so an
    interrupted command leaves none)."""
    _prog[0] = prog
    try:
        return int(run(args) or 0)
    except BaseException as err:
        if interrupted():  # a real signal: end now, without the slow and noisy interpreter shutdown
            _end_now()
        if isinstance(err, KeyboardInterrupt):
            _say_interrupted(prog)
            return INTERRUPTED
        if isinstance(err, (MVPSError, OSError, ValueError)):
            print(f"{prog}: error: {err}", file=sys.stderr)
            return 1
        raise


def supervise(module: str, argv: list[str], prog: str) -> int:
    """Run ``python -m module argv`` in a child process and return its exit code, so that a signal
    stops it within :data:`STOP_SECONDS` even while it is inside a library call that holds the
    GIL (Open3D's UV atlas of a large mesh holds it for seconds, and no Python-level handler or
    watchdog thread runs until it returns).

    SIGINT and SIGTERM are passed on to the child, which cleans up and ends itself
    (:func:`stop_on_signals`); a child still running shortly after its own deadline is killed, and
    the supervisor prints ``PROG: interrupted`` (unless the child did) and returns 130. The child
    inherits stdin, stdout and stderr.
    """
    import select
    import subprocess
    import time

    said_r, said_w = os.pipe()
    package_root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = {**os.environ, SAID_FD: str(said_w),  # the child imports this same o3d_mvps
           "PYTHONPATH": os.pathsep.join(p for p in (package_root, os.environ.get("PYTHONPATH")) if p)}
    child = subprocess.Popen([sys.executable, "-m", module, *argv], env=env, pass_fds=(said_w,))
    os.close(said_w)
    received = []

    def forward(signum, frame):
        if not received:
            received.append(time.monotonic())
        try:
            child.send_signal(signum)
        except OSError:
            pass

    previous = {sig: signal.signal(sig, forward) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        while True:
            try:
                return child.wait(timeout=0.05)
            except subprocess.TimeoutExpired:
                if received and time.monotonic() - received[0] > STOP_SECONDS + 0.25:
                    child.kill()
                    child.wait()
                    child_said = bool(select.select([said_r], [], [], 0)[0]) and os.read(said_r, 1) == b"1"
                    if not child_said:
                        print(f"{prog}: interrupted", file=sys.stderr, flush=True)
                    return INTERRUPTED
    finally:
        os.close(said_r)
        restore_signals(previous)


def _command_name(argv: list[str]) -> str:
    """'o3d-mvps COMMAND' from the arguments (the first one that is a subcommand)."""
    command = next((a for a in argv if a in SUBCOMMANDS or a == "convert"), None)
    return "o3d-mvps" if command is None else f"o3d-mvps {command}"


def main(argv=None) -> int:
    """The ``o3d-mvps`` command line. Called without ``argv`` (the console script, ``python -m
    o3d_mvps``), the command runs in a child process under :func:`supervise`."""
    if argv is None and not os.environ.get(SAID_FD) and os.name == "posix":
        return supervise("o3d_mvps", sys.argv[1:], _command_name(sys.argv[1:]))
    prog = _command_name(sys.argv[1:] if argv is None else argv)
    previous = stop_on_signals(prog)
    try:
        try:  # Ctrl-C while the subcommands' modules (Open3D) load: the same one line
            args = build_parser().parse_args(argv)
        except BaseException as err:
            if interrupted():
                _end_now()
            if isinstance(err, KeyboardInterrupt):
                _say_interrupted(prog)
                return INTERRUPTED
            raise
        from .outputs import quiet_output

        with quiet_output(getattr(args, "quiet", False)):
            return run_handler(f"o3d-mvps {args.command}", args.handler, args)
    finally:
        restore_signals(previous)


if __name__ == "__main__":
    sys.exit(main())
