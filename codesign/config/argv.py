"""The command line before Hydra reads it (codesign/__main__.py): a leading ``~`` of the run folders expanded, as
every path key of codesign expands it, and an override Hydra cannot parse explained with a hint on quoting."""
from __future__ import annotations

import contextlib
import io
import os

# Hydra takes these folders as they are: hydra.run.dir="~/x" wrote into a folder literally named '~' under the
# current one, while mask.init="~/..." (and every other path key) is expanded
RUN_DIR_KEYS = ("hydra.run.dir", "hydra.sweep.dir")
_QUOTES = ("'", '"')


def expand_run_dirs(args: list[str]) -> list[str]:
    """``args`` with a leading ``~`` (or ``~user``) of a run-folder override (RUN_DIR_KEYS, also with + or ++ and
    Hydra's quotes) expanded to the home folder; every other argument unchanged."""
    out = []
    for arg in args:
        key, eq, value = arg.partition("=")
        if eq and key.lstrip("+") in RUN_DIR_KEYS:
            quote = value[0] if len(value) >= 2 and value[0] in _QUOTES and value[-1] == value[0] else ""
            inner = value[1:-1] if quote else value
            if inner.startswith("~"):
                arg = f"{key}={quote}{os.path.expanduser(inner)}{quote}"
        out.append(arg)
    return out


def override_parse_problem(args: list[str]) -> str | None:
    """Hydra's own message for an override of ``args`` its grammar cannot parse, followed by one line of hint on
    quoting (Hydra's lexer error alone never says that a value with a space was cut in two by the shell); None
    when every override parses (or the flags themselves are wrong: Hydra reports those)."""
    from hydra._internal.utils import get_args_parser
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    try:
        with contextlib.redirect_stderr(io.StringIO()):  # a bad flag is Hydra's to report, once
            overrides = get_args_parser().parse_known_args(args)[0].overrides
    except SystemExit:
        return None
    try:
        OverridesParser.create().parse_overrides(overrides=overrides)
    except OverrideParseException as err:
        return f"{err}\ncodesign: hint: {quoting_hint(overrides, err.override)}"
    return None


def quoting_hint(overrides: list[str], bad: str) -> str:
    """One line on how to quote ``bad``: the rest of the value before it when the shell cut a value at a space
    (``input=/tmp/a b.png`` reaches Hydra as two overrides), else a value's special characters."""
    at = overrides.index(bad) if bad in overrides else -1
    if "=" not in bad and at > 0 and "=" in overrides[at - 1]:
        key, _, value = overrides[at - 1].partition("=")
        return (f"'{bad}' looks like the rest of {key}'s value, cut at a space by the shell: quote the whole "
                f"override, the value in double quotes: '{key}=\"{value} {bad}\"'")
    key, _, value = bad.partition("=")
    return (f"a value holding spaces or any of ()[]{{}}=,:'\"\\ must be quoted for Hydra inside the shell's quotes, "
            f"e.g. '{key or 'key'}=\"{value or 'a value'}\"'")


# Hydra keys that name a file or folder Hydra writes to itself, outside the run folder's guard: the run's record
# (codesign writes RUN/.hydra itself, without following links: hydra.output_subdir is null) and the log files of
# Hydra's logging config (the run's log is RUN/<task>.log, opened by the guard)
WRITES_ELSEWHERE = ("hydra.output_subdir",)
LOG_FILE_KEYS = ("hydra.job_logging.", "hydra.hydra_logging.")


def hydra_write_path_error(args: list[str]) -> str | None:
    """The configuration error for an override that would have Hydra write a file where the run-folder guard never
    looks (hydra.output_subdir, a log handler's filename: an audit had the run's record written outside its folder
    and its log appended to a user's file), or None."""
    for arg in args:
        key, eq, value = arg.partition("=")
        name = key.lstrip("+~")
        if not eq:
            continue
        by_log = name.startswith(LOG_FILE_KEYS) and name.rsplit(".", 1)[-1] == "filename"
        if name in WRITES_ELSEWHERE or by_log:
            return (f"{name} = {value!r}: codesign writes the run's record (.hydra/) and its log into the run folder "
                    "itself, through the run-folder guard; a file of Hydra's elsewhere is not allowed: choose the "
                    "folder with hydra.run.dir=PATH (or hydra.sweep.dir=PATH with -m)")
    return None
