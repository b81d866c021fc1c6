"""The command-line boundary: flags from the config dataclasses, one-line errors, clean signals.

Every script describes what it runs with one frozen dataclass (its fields, nested configs
included, carry the defaults and the help text as comments or docstrings) and calls
:func:`parse` with a named preset as the default. Nested configs are flattened: a field
``learner.eta`` is the flag ``--eta`` (names are unique across a script's config tree; tyro
refuses duplicates).

:func:`parse` turns every bad argument (an unknown flag, a value of the wrong type, a value a
config's ``__post_init__`` rejects, a used ``--out`` folder) into one line on stderr and exit
code 2, before anything is compiled. :func:`command` wraps a script's ``main``: Ctrl-C (SIGINT)
or SIGTERM ends the run cleanly (its run folder marked failed and renamed, one line, exit code
130 or 143) at once, even in the middle of an XLA compilation.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import tyro

T = TypeVar("T")
F = TypeVar("F", bound=Callable[..., Any])
_state = threading.local()  # .active: a command() is running in this thread


_RULES = {
    "given": ("given", lambda v: True),  # for tuples: at least one value
    "count": (
        "an integer >= 1",
        lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 1,
    ),
    "seed": (
        "an integer >= 0",
        lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
    ),
    "positive": (
        "finite and > 0",
        lambda v: isinstance(v, (int, float)) and math.isfinite(v) and v > 0,
    ),
    "non_negative": (
        "finite and >= 0",
        lambda v: isinstance(v, (int, float)) and math.isfinite(v) and v >= 0,
    ),
    "fraction": (
        "in [0, 1]",
        lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v <= 1,
    ),
}


def require(obj: Any, rule: str, *names: str) -> None:
    """Checks fields of a script's config (for its ``__post_init__``).

    Args:
        obj: the config.
        rule: ``"given"`` (a tuple with at least one value), ``"count"`` (an integer >= 1),
            ``"seed"`` (an integer >= 0), ``"positive"`` (finite and > 0), ``"non_negative"``
            (finite and >= 0) or ``"fraction"`` (in [0, 1]); a tuple field must hold at least
            one value and each must pass.
        *names: the fields.

    Raises:
        ValueError: naming the flag (``--field-name``), the rule and the value.
    """
    what, ok = _RULES[rule]
    for name in names:
        v = getattr(obj, name)
        flag = f"--{name.replace('_', '-')}"
        values = v if isinstance(v, tuple) else (v,)
        if not values:
            raise ValueError(f"{flag}: needs at least one value")
        if not all(ok(x) for x in values):
            each = "each value " if isinstance(v, tuple) else ""
            raise ValueError(f"{flag}: {each}must be {what}, got {v!r}")


def usage_error(message: str, prog: str | None = None) -> SystemExit:
    """Prints ``<prog>: error: <message>`` (one line) on stderr; returns ``SystemExit(2)`` to
    raise.
    """
    prog = os.path.basename(sys.argv[0]) if prog is None else os.path.basename(prog)
    print(f"{prog}: error: {' '.join(str(message).split())}", file=sys.stderr, flush=True)
    return SystemExit(2)


def _flag(argument) -> str:
    try:
        return str(argument.lowered.name_or_flags[0])
    except (AttributeError, IndexError, TypeError):
        return "an argument"


def _one_line(event) -> str | None:
    """The one-line message of a tyro parse-error event (None: an event this does not know)."""
    kind = type(event).__name__
    argument = getattr(event, "argument", None)
    if kind == "InstantiationFailure":
        where = f"{_flag(argument)}: " if argument is not None else ""
        return f"{where}{event.message}"
    if kind == "UnrecognizedArgs":
        return f"unrecognized arguments: {' '.join(event.tokens)}"
    if kind == "InvalidChoice":
        return f"{_flag(argument)}: {event.value!r} is not one of {', '.join(event.choices)}"
    if kind == "BadValue":
        return f"{_flag(argument)}: missing or extra value"
    if kind == "MissingArgs":
        return f"missing {', '.join(_flag(a.arg) for a in event.missing_arguments)}"
    return None


@contextlib.contextmanager
def _one_line_errors(prog: str | None):
    """Turns tyro's errors into one line (its parse-error hook, a private API of tyro 1.0;
    without it, tyro's own boxed message, also exit code 2).
    """
    try:
        from tyro import _errors
    except ImportError:
        _errors = None
    if _errors is None or not hasattr(_errors, "on_parse_error"):
        yield
        return

    def hook(event) -> None:
        message = _one_line(event)
        if message is not None:
            raise usage_error(f"{message} (see --help)", prog)

    with _errors.on_parse_error(hook):
        yield


def parse(default: T, argv: Sequence[str] | None = None, description: str | None = None) -> T:
    """Parses ``argv`` (default: ``sys.argv[1:]``) into a copy of ``default`` with flags applied.

    A config with both an ``out`` and an ``overwrite`` field writes a run folder
    (:func:`hec_jax.runs.run_folder`): an existing non-empty ``out`` without ``overwrite`` is
    refused here, before anything runs.

    Args:
        default: a frozen dataclass instance: the preset whose fields are the defaults.
        argv: command-line arguments; None reads ``sys.argv``.
        description: the ``--help`` text (usually the script's docstring).

    Returns:
        An instance of ``type(default)``; its ``__post_init__`` checks ran on it.

    Raises:
        SystemExit: code 2 after one line on stderr for any bad argument; code 0 after
            ``--help``.
    """
    from hec_jax.runs import note_parsed_args

    note_parsed_args(sys.argv[1:] if argv is None else list(argv))  # config.json's parsed_args
    with _one_line_errors(None):
        config = tyro.cli(
            type(default),
            default=default,
            args=argv,
            description=description,
            config=(tyro.conf.OmitArgPrefixes,),
        )
    if hasattr(config, "out") and hasattr(config, "overwrite"):
        from hec_jax.runs import check_out

        try:
            check_out(config.out, config.overwrite)
        except FileExistsError as e:
            raise usage_error(str(e)) from None
    return config


def _end_on_signal(signum: int) -> None:
    """Ends the process after SIGINT/SIGTERM: the open run folder marked failed and renamed,
    one line on stderr, exit code 128 + signum, without Python's teardown (see
    :func:`_clean_signals`).
    """
    from hec_jax.progress import restore_terminal
    from hec_jax.runs import fail_active_run

    name = signal.Signals(signum).name
    try:
        restore_terminal()
        failed = fail_active_run(f"interrupted ({name})")
        where = f"; what the run wrote is in {failed}" if failed is not None else ""
        print(f"interrupted ({name}){where}", file=sys.stderr, flush=True)
        sys.stdout.flush()
    finally:
        os._exit(128 + signum)


@contextlib.contextmanager
def _clean_signals():
    """SIGINT and SIGTERM end the process through :func:`_end_on_signal`, from a watcher thread.

    Why not Python's KeyboardInterrupt: it is raised wherever the main thread next runs Python
    code, which during an XLA compilation (tens of seconds) is only once the compilation is
    over. Right after one that is often JAX's garbage-collector callback, where the exception is
    printed and dropped ("Exception ignored in: _xla_gc_callback"), so the run went on as if
    nothing happened (jax-ml/jax#18246); when it does propagate, the process crashed in the
    interpreter's teardown (exit 139, no Python frame left: native XLA/MuJoCo state torn down
    out of order; jax-ml/jax#15810 is of the kind). Measured on catching (``--eye truth --seeds
    1 --swings 1``, SIGINT 6-22 s in, 2 CPU cores): of 10 tries, 3 segmentation faults and 3
    Ctrl-C dropped. So the signals only wake a thread (Python's wakeup fd, written by the
    C-level handler at once; XLA releases the GIL while it compiles), which fails the run
    folder and leaves through ``os._exit`` (no teardown, nothing left to crash). Only in the
    main thread; a signal ignored at start (SIG_IGN, e.g. SIGINT of a background job) stays
    ignored; the previous handlers come back on exit.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) is not signal.SIG_IGN:
            previous[sig] = signal.signal(sig, lambda *_: None)
    old_fd = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)

    def watch() -> None:
        while True:
            try:
                data = os.read(read_fd, 1)
            except OSError:
                return
            if not data:  # the write end was closed: the command is over
                return
            if data[0] in previous:
                _end_on_signal(data[0])

    watcher = threading.Thread(target=watch, name="hec_jax-signals", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        signal.set_wakeup_fd(old_fd)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        os.close(write_fd)
        watcher.join(timeout=5)
        os.close(read_fd)


def command(main: F) -> F:
    """Decorates a script's ``main(argv=None)``: while it runs, Ctrl-C (SIGINT) and SIGTERM end
    the process cleanly (the open run folder marked ``failed`` with "interrupted (SIGINT)" and
    renamed ``<out>.failed-<time>``, the line ``interrupted (SIGINT)`` on stderr, exit code 130;
    143 for SIGTERM). Nested use (a script's ``main`` over :func:`hec_jax.loop.cli.main_for`)
    installs the handlers once.
    """

    @functools.wraps(main)
    def wrapper(*args, **kwargs):
        from hec_jax.runs import script_arguments  # the arguments its run folders record

        if getattr(_state, "active", False):
            with script_arguments():
                return main(*args, **kwargs)
        _state.active = True
        try:
            with _clean_signals(), script_arguments():
                return main(*args, **kwargs)
        finally:
            _state.active = False

    return wrapper  # type: ignore[return-value]
