"""The ``plantsplat`` command line: one sub-command per stage, discovered from ``plantsplat.commands``.

Errors a user can cause are printed as one line (``error: ...``) with a non-zero exit code; a
traceback is shown only with ``--verbose``.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import pkgutil
import signal
import sys
import threading
from typing import Annotated

import plantsplat.commands as command_modules
from plantsplat import __version__
from plantsplat.errors import PlantsplatError

EXIT_INTERRUPTED = 130
"""Ctrl-C (128 + SIGINT), as shells report it."""
EXIT_TERMINATED = 143
"""SIGTERM (128 + SIGTERM), as shells report it."""

DESCRIPTION = (
    "plantsplat: from a phone video of a potted plant (with a 10 cm ArUco cube) to a clean 3D "
    "Gaussian Splatting model and metric traits. Global flags: --verbose (debug log, tracebacks), "
    "--quiet (warnings only), --version."
)


def discover_commands():
    commands = []
    for info in pkgutil.iter_modules(command_modules.__path__):
        module = importlib.import_module(f"{command_modules.__name__}.{info.name}")
        cmd = getattr(module, "COMMAND", None)
        if cmd is not None:
            commands.append(cmd)
    commands.sort(key=lambda c: (c.order, c.name))
    return commands


def usage_line(text: str, argv: list[str]) -> str:
    """tyro's usage error (a box of several paragraphs) said in one line: what is wrong, the option it
    suggests, and where the help is.

    Example:
        >>> usage_line("Unrecognized options\\n----\\nUnrecognized options: --nmu\\n----\\nPerhaps you meant:\\n"
        ...            "    --num INT\\n", ["frames", "--nmu"])
        'Unrecognized options: --nmu; did you mean --num? (see `plantsplat frames --help`)'
    """
    rows = [ln.strip().strip("│╭╮╰╯").strip() for ln in text.splitlines()]
    paragraphs: list[str] = []  # the text between rules and blank lines, each joined into one line
    current: list[str] = []
    for r in rows + [""]:
        if r and not set(r) <= set("-─ "):
            current.append(r)
        elif current:
            paragraphs.append(" ".join(current))
            current = []
    body = paragraphs[1] if len(paragraphs) > 1 else (paragraphs[0] if paragraphs else "invalid arguments")
    said = [body]
    for i, par in enumerate(paragraphs):
        if par.startswith("Perhaps you meant:"):
            said.append(f"did you mean {(par.split()[3:] or paragraphs[i + 1:i + 2] or ['?'])[0]}?")
        elif par.startswith("Available subcommands"):
            said.append(par)
    command = next((a for a in argv if not a.startswith("-")), None)
    where = f"plantsplat {command} --help" if command and len(said) == 1 or "did" in said[-1] else "plantsplat --help"
    return "; ".join(said) + f" (see `{where}`)"


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--version" in argv:
        print(f"plantsplat {__version__}")
        return 0
    # deferred: `plantsplat --version` answers before tyro, rich and numpy load (about 0.2 s)
    import tyro

    from plantsplat.log import console, setup_logging

    verbose = "--verbose" in argv or "-v" in argv
    quiet = "--quiet" in argv or "-q" in argv
    argv = [a for a in argv if a not in ("--verbose", "-v", "--quiet", "-q")]
    setup_logging(verbose=verbose, quiet=quiet)

    commands = discover_commands()
    by_type = {c.config: c for c in commands}
    said = io.StringIO()
    try:
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            cfg = tyro.extras.subcommand_cli_from_dict(
                {c.name: Annotated[c.config, tyro.conf.arg(help=c.help)] for c in commands},
                args=argv,
                prog="plantsplat",
                description=DESCRIPTION,
            )
    except SystemExit as exc:  # --help, or tyro's own usage error (exit 2)
        if not exc.code:
            sys.stdout.write(said.getvalue())
            return 0
        console.print(f"[bold red]error:[/] {usage_line(said.getvalue(), argv)}", markup=True, highlight=False,
                      soft_wrap=True)
        return int(exc.code) if isinstance(exc.code, int) else 2
    sys.stdout.write(said.getvalue())

    cmd = by_type[type(cfg)]
    with sigterm_as_interrupt():
        return _run_command(cmd, cfg, verbose, console)


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, a scheduler), raised in the main thread like Ctrl-C's KeyboardInterrupt so that
    it takes the same path: stage records left ``running`` (resumable), finished outputs kept, one line."""


@contextlib.contextmanager
def sigterm_as_interrupt():
    """Turn SIGTERM into :class:`Terminated` for the block (in the main thread; elsewhere nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def terminated(signum, frame):
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _run_command(cmd, cfg, verbose: bool, console) -> int:
    """Run the parsed command; every way it can end becomes an exit code and at most one line (on ``console``, the
    log's rich console)."""
    try:
        code = cmd.run(cfg)
    except PlantsplatError as exc:
        if verbose:
            console.print_exception()
        console.print(f"[bold red]error:[/] {exc}", markup=True, highlight=False, soft_wrap=True)
        return exc.exit_code
    except KeyboardInterrupt as exc:
        return _interrupted(exc, console)
    except OSError as exc:  # the disk or the file system, said in words
        from plantsplat.io import os_error_message  # deferred: it loads numpy (see main)

        if verbose:
            console.print_exception()
        console.print(f"[bold red]error:[/] {os_error_message(exc)}", markup=True, highlight=False, soft_wrap=True)
        return 1
    except Exception as exc:  # an unexpected failure: one line, traceback only with --verbose
        if interrupt_behind(exc) is not None:  # Ctrl-C or SIGTERM that landed inside a C library's callback
            return _interrupted(interrupt_behind(exc), console)
        if verbose:
            console.print_exception()
        console.print(
            f"[bold red]error:[/] {cmd.name} failed: {type(exc).__name__}: {exc} "
            "(re-run with --verbose for details; finished outputs are kept)",
            markup=True,
            highlight=False,
            soft_wrap=True,
        )
        return 1
    return int(code or 0)


def interrupt_behind(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C or SIGTERM behind ``exc``: one raised inside a callback from C (numba, torch) comes out as a
    ``SystemError`` ("returned a result with an exception set") caused by it."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _interrupted(exc: KeyboardInterrupt, console) -> int:
    what = "terminated (SIGTERM)" if isinstance(exc, Terminated) else "interrupted"
    console.print(f"{what}: finished outputs are kept; re-run the same command to resume", soft_wrap=True)
    return EXIT_TERMINATED if isinstance(exc, Terminated) else EXIT_INTERRUPTED


def entry() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entry()
