"""The ``slam-gym`` command line (docs/ARCHITECTURE.md, "The command line and its output files")."""

from __future__ import annotations

import argparse
import ast
import importlib
import re
import sys

COMMAND_MODULES = ("simulate", "reproduce", "benchmark", "compare", "headroom", "train",
                   "threshold-rule", "front", "fingerprint", "speed", "distil")


class Parser(argparse.ArgumentParser):
    """argparse's parser, with its errors in one line (the usage is one ``--help`` away)."""

    def error(self, message):
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (usage: {self.prog} --help)\n")


def option_flags(parser: argparse.ArgumentParser) -> dict[str, str]:
    """Each option's destination -> the option as a user types it (its long form; a positional
    argument's metavar)."""
    flags = {}
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        if action.option_strings:
            flags[action.dest] = max(action.option_strings, key=len)
        else:
            flags[action.dest] = action.metavar or action.dest.upper()
    return flags


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="slam-gym",
        description="The local-to-global interface of hybrid SLAM as a decision problem.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--debug", action="store_true",
                        help="show the whole traceback of an error instead of one line")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        module = importlib.import_module(f"slam_gym.commands.{name.replace('-', '_')}")
        module.add_parser(subparsers)
    _name_options(subparsers, {})
    return parser


def _name_options(subparsers: argparse._SubParsersAction, outer: dict[str, str]) -> None:
    """Give every (sub)command's namespace its :func:`option_flags` (with its parents'), so an
    error can name the option as the user typed it."""
    for sub in subparsers.choices.values():
        flags = outer | option_flags(sub)
        sub.set_defaults(option_flags=flags)
        for action in sub._actions:
            if isinstance(action, argparse._SubParsersAction):
                _name_options(action, flags)


BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread_per_process() -> None:
    """Parallelism is across processes (one run per core): BLAS gets one thread per process.

    Multi-threaded OpenBLAS slows the small matrix products of the filters and SciPy's L-BFGS-B
    badly. The variables reach the worker processes started later; threadpoolctl limits the BLAS
    this process has already loaded.
    """
    import os

    from threadpoolctl import threadpool_limits

    for name in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
    threadpool_limits(1)


EXIT_USAGE = 2
"""An invalid or conflicting option value, an unusable ``--out``, a policy or model that cannot
be loaded: nothing ran (argparse exits 2 for its own errors too)."""
EXIT_FAILED = 1
"""The command could not run: the output is locked by another run, an optional dependency is
missing; also ``speed --compare`` and ``fingerprint`` report a failed check with it."""
EXIT_INTERRUPTED = 130
"""Ctrl-C (128 + SIGINT, the shell's convention)."""
# A command that finished with error rows exits slam_gym.commands.runs.EXIT_RUN_ERRORS (3).


OPTIONAL_EXTRAS = {"ray": "ray", "sb3_contrib": "contrib"}
"""Top-level module -> the extra of pyproject.toml that installs it."""


FIELD_OPTIONS = {"seeds": "trials", "clutter_level": "clutter_levels", "env_id": "env"}
"""The Python names of options (:func:`slam_gym.evaluation.benchmark`'s, the env's) whose
command-line option has another destination (used where the name is not an option itself); an
env keyword argument ``NAME`` is shorthand ``env_NAME``'s (:mod:`slam_gym.commands.envargs`)."""

EXIT_CLOSED_PIPE = 141
"""The output pipe was closed by its reader (``| head -1``): 128 + SIGPIPE, as a Unix tool that
the signal ends (the shell's convention); nothing more is printed."""

_INVALID = re.compile(r"(\w+)=(.*?) is invalid((?::| with| without| for) .*)", re.S)


def _plain(value) -> str:
    """A value as it would be typed: a list comma-separated, a whole float without its '.0'."""
    if isinstance(value, (list, tuple)):
        return ",".join(_plain(v) for v in value)
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)


def typed_text(argv: list[str], flag: str) -> str | None:
    """What followed ``flag`` on the command line (``--flag VALUE`` or ``--flag=VALUE``; the
    last one given), or None."""
    found = None
    for i, token in enumerate(argv):
        if token == flag and i + 1 < len(argv):
            found = argv[i + 1]
        elif token.startswith(flag + "="):
            found = token[len(flag) + 1:]
    return found


def option_message(exc: ValueError, args=None, argv: list[str] | None = None) -> str:
    """The message of an invalid option value, naming the option as the user typed it
    (``--particles -3 is invalid: must be ...``) where the message names one of the command's
    options in the form every layer validates with (:func:`filters.validation.require`:
    ``field=value is invalid: ...``; also ``... is invalid with ...``); else the message
    unchanged. When the value at fault is part of what was typed (one level of
    ``--clutter-levels 0,5``) it is named too."""
    match = _INVALID.fullmatch(str(exc))
    if match is None:
        return str(exc)
    field, rest = match.group(1), match.group(3)
    try:
        value = ast.literal_eval(match.group(2))
    except (ValueError, SyntaxError, MemoryError, RecursionError):
        value = match.group(2)
    flags = getattr(args, "option_flags", None) or {}
    dest = next((d for d in (field, f"env_{field}", FIELD_OPTIONS.get(field)) if d in flags),
                None)
    if dest is None:
        return str(exc)
    flag = flags[dest]
    typed = typed_text(list(argv or []), flag) if flag.startswith("-") else None
    if typed is None:
        if getattr(args, dest, None) is None:  # not from this option (e.g. --env-kwargs)
            return str(exc)
        typed = _plain(getattr(args, dest, value))
    same = typed == _plain(value)
    if not same:
        try:
            same = float(typed) == float(value)
        except (TypeError, ValueError):
            pass
    what = "" if same else f" ({field}={value!r})"
    shown = typed if typed and " " not in typed else repr(typed)
    return f"{flag} {shown} is invalid{what}{rest}"


def one_line_error(exc: BaseException, args=None, argv: list[str] | None = None
                   ) -> tuple[str, int] | None:
    """The one-line message and exit code of a foreseeable failure, or None for a bug (whose
    traceback is shown). ``args`` and ``argv``, the parsed and the typed command line, let an
    invalid value's message name the option as typed (:func:`option_message`)."""
    from slam_gym.evaluation.results import ResultsLockedError

    if isinstance(exc, KeyboardInterrupt):
        return (str(exc) or "interrupted; the runs finished so far are kept in --out's "
                "results.jsonl: rerun the same command to resume"), EXIT_INTERRUPTED
    if isinstance(exc, ValueError):
        return option_message(exc, args, argv), EXIT_USAGE
    if isinstance(exc, FileNotFoundError):  # a missing model names its path
        return str(exc), EXIT_USAGE
    if isinstance(exc, ResultsLockedError):
        return str(exc), EXIT_FAILED
    if isinstance(exc, ImportError):
        if "pip install" in str(exc):  # the message names the extra already
            return str(exc), EXIT_FAILED
        extra = OPTIONAL_EXTRAS.get((exc.name or "").partition(".")[0])
        hint = (f": it is the optional dependency of extra [{extra}], pip install "
                f"'slam-gym[{extra}]'" if extra else "")
        return f"cannot import {exc.name or 'a module'} ({exc}){hint}", EXIT_FAILED
    return None


def main(argv: list[str] | None = None) -> int:
    """Run one command; its exit code: 0, or :data:`EXIT_USAGE`, :data:`EXIT_FAILED`,
    ``EXIT_RUN_ERRORS`` (3: some runs are error rows), :data:`EXIT_INTERRUPTED`. Foreseeable
    failures print one line (``--debug``: the traceback too)."""
    from slam_gym.commands.common import configure_logging

    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = build_parser().parse_args(argv)
    except BrokenPipeError:  # --help into a closed pipe
        return _closed_pipe()
    configure_logging(args.verbose)
    one_blas_thread_per_process()
    try:
        code = int(args.run(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
        return code
    except BrokenPipeError:
        return _closed_pipe()
    except (Exception, KeyboardInterrupt) as exc:
        known = one_line_error(exc, args, argv)
        if known is None or args.debug:
            raise
        message, code = known
        print(f"slam-gym {args.command}: error: {message}", file=sys.stderr)
        return code


def _closed_pipe() -> int:
    """The reader of stdout went away: end quietly (:data:`EXIT_CLOSED_PIPE`). stdout is pointed
    at /dev/null so that the interpreter's flush at exit cannot fail again."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    return EXIT_CLOSED_PIPE


if __name__ == "__main__":
    sys.exit(main())
