"""The `mvrecon` command: argument parsing, logging, exit codes. No algorithm lives here.

Each subcommand is a module in `mvrecon/commands/` with a docstring (its help line), an `ORDER` number (its
place in `--help`), `add_arguments(parser)` and `run(args) -> int`; the module's name is the command's name
(underscores become dashes). `HOLDS_OUTPUT = True` makes the CLI hold its `-o` folder for the run, so that a
second run into it stops in one line instead of breaking both. A run imports only its own command's module,
which imports what the command needs at its top; the list of commands (`mvrecon --help`, a mistyped command)
reads each module's docstring and `ORDER` from its source instead of importing every command's libraries.
"""

import argparse
import ast
import codecs
import contextlib
import errno
import importlib
import io
import logging
import os
import pkgutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

from . import __version__, commands, zlib_order
from .errors import DiskFull, InputError
from .executor import one_blas_thread, wait_for_ended_pools
from .interrupts import STOPPING, keep_handlers_after_import
from .io.files import ESCAPE, hold_folder
from .progress import clear_line, set_enabled
from .startup import keep_freed_memory


def _command_names() -> list[str]:
    """The commands' module names (`reconstruct`, `compare`, ...), in no particular order."""
    return [info.name for info in pkgutil.iter_modules(commands.__path__) if not info.name.startswith("_")]


def _described(name: str) -> tuple[int, str]:
    """(ORDER, docstring) of the command module `name`, read from its source without importing it: importing
    every command's libraries to list them took `mvrecon --help` from 0.4 s to 1.9 s of CPU."""
    source = Path(commands.__file__).with_name(f"{name}.py").read_text(encoding="utf-8")
    tree = ast.parse(source)
    order = next((node.value.value for node in tree.body if isinstance(node, ast.Assign)
                  and any(isinstance(t, ast.Name) and t.id == "ORDER" for t in node.targets)
                  and isinstance(node.value, ast.Constant)), 100)
    return order, ast.get_docstring(tree, clean=False) or ""


def _command_in(argv: list[str]) -> str | None:
    """The command `argv` runs: its first word that is not an option (the options before a command take no
    value), or None when `-h`/`--help` comes first, which lists every command."""
    for arg in argv:
        if arg in ("-h", "--help"):
            return None
        if not arg.startswith("-"):
            return arg
    return None


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of the command `only` (as typed) with all its options, importing that command's module
    alone; without `only`, or with one that is no command, the list of every command (their help lines, no
    options), so that `--help` and argparse's error for a mistyped command name them all."""
    parser = argparse.ArgumentParser(prog="mvrecon",
                                     description="Structure from motion in Python, validated against COLMAP.")
    parser.add_argument("--version", action="version", version=f"mvrecon {__version__}")
    # -v/-q are accepted before the command too (`mvrecon -q reconstruct ...`); own dests, as a subcommand's
    # defaults would overwrite the same dest
    parser.add_argument("-v", "--verbose", dest="global_verbose", action="count", default=0, help=argparse.SUPPRESS)
    parser.add_argument("-q", "--quiet", dest="global_quiet", action="store_true", help=argparse.SUPPRESS)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    common.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors, no progress bars")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    names = _command_names()
    wanted = None if only is None else only.replace("-", "_")
    if wanted in names:
        module = importlib.import_module(f"mvrecon.commands.{wanted}")
        p = _add_command(sub, common, wanted, module.__doc__ or "")
        module.add_arguments(p)
        p.set_defaults(_module=module)
        return parser
    listed = []
    for name in names:
        order, doc = _described(name)
        listed.append((order, name, doc))
    for _, name, doc in sorted(listed):
        _add_command(sub, common, name, doc)
    return parser


def _add_command(sub, common: argparse.ArgumentParser, name: str, doc: str) -> argparse.ArgumentParser:
    """The sub-parser of the command module `name`, its help line the docstring's first line."""
    doc = doc.strip()
    first = doc.splitlines()[0] if doc else name
    return sub.add_parser(name.replace("_", "-"), parents=[common], help=first, description=doc,
                          formatter_class=argparse.RawDescriptionHelpFormatter)


def _setup_logging(verbose: int, quiet: bool) -> None:
    level = logging.WARNING if quiet else (logging.DEBUG if verbose >= 2 else logging.INFO)
    # other libraries log at INFO at most: -vv is for mvrecon's own debug lines (Pillow's would log every PNG chunk)
    logging.basicConfig(level=max(level, logging.INFO),
                        format="%(message)s" if verbose == 0 else "%(asctime)s %(name)s: %(message)s",
                        stream=sys.stderr)
    for handler in logging.getLogger().handlers:
        handler.addFilter(clear_line)  # a message clears the progress bar's line instead of running on after it
    logging.getLogger("mvrecon").setLevel(level)
    set_enabled(not quiet)


_interrupt = threading.Event()
_signal_received: list[int] = []  # the stopping signal received, if any


def _on_stop_signal(signum, frame):
    """Ctrl-C, or SIGTERM (`timeout`, `kill`, a batch scheduler): the run stops the same way."""
    _interrupt.set()
    _signal_received[:] = [signum]
    raise KeyboardInterrupt


def _interrupted(module) -> int:
    """Exit 130 (Ctrl-C) or 143 (SIGTERM) with one line; the command says what a rerun continues from (its
    ON_INTERRUPT), if anything."""
    clear_line()
    hint = getattr(module, "ON_INTERRUPT", "")
    terminated = _signal_received == [signal.SIGTERM]
    print(f"mvrecon: {'terminated (SIGTERM)' if terminated else 'interrupted'}{'; ' + hint if hint else ''}",
          file=sys.stderr)
    return 143 if terminated else 130


def main(argv: list[str] | None = None) -> int:
    if zlib_order.TAKEN_OVER:  # pycolmap was imported first: a PNG written here would abort this process
        return _in_fresh_process(argv)
    if argv is None:  # the `mvrecon` process itself, before numpy is loaded
        one_blas_thread()
        keep_freed_memory()
    # file names that are not UTF-8 printed as \xNN, as the log lines name them (a UTF-8 terminal's strict
    # stdout raised UnicodeEncodeError instead)
    for stream in (sys.stdout, sys.stderr):
        if isinstance(stream, io.TextIOWrapper):
            stream.reconfigure(errors=ESCAPE)
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = {s: signal.signal(s, _on_stop_signal) for s in STOPPING} if in_main_thread else {}
    keep_handlers_after_import("pycolmap")
    _interrupt.clear()
    _signal_received.clear()
    try:
        code = _run(argv)
    except KeyboardInterrupt:  # before a command was chosen (while the parser imports the command modules)
        code = _interrupted(None)
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    return code


def _in_fresh_process(argv) -> int:
    """`main(argv)` run by a new interpreter (`python -m mvrecon.cli`), for a process whose zlib pycolmap has taken
    over (`zlib_order`); returns its exit code. Its output goes where this process's does (through this process
    when a stream has no file descriptor: a notebook's), and Ctrl-C or SIGTERM here stops it as it would this
    run: it has a process group of its own, so that it gets the signal once, from here."""
    argv = sys.argv[1:] if argv is None else [os.fspath(a) for a in argv]
    env = dict(os.environ)  # the same mvrecon package, wherever this process found it
    env["PYTHONPATH"] = os.pathsep.join(filter(None, (str(Path(__file__).resolve().parents[1]),
                                                      env.get("PYTHONPATH"))))
    targets = []
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
        try:
            targets.append(stream.fileno())
        except (AttributeError, OSError, ValueError):  # io.UnsupportedOperation, a closed stream
            targets.append(subprocess.PIPE)
    proc = subprocess.Popen([sys.executable, "-m", "mvrecon.cli", *argv], env=env, stdout=targets[0],
                            stderr=targets[1], process_group=0)

    def forward(pipe, stream):
        decoder = codecs.getincrementaldecoder("utf-8")(errors="replace")
        for chunk in iter(lambda: pipe.read1(65536), b""):
            stream.write(decoder.decode(chunk))
            stream.flush()

    threads = [threading.Thread(target=forward, args=(pipe, stream), daemon=True)
               for pipe, stream in ((proc.stdout, sys.stdout), (proc.stderr, sys.stderr)) if pipe is not None]
    for thread in threads:
        thread.start()
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = {s: signal.signal(s, lambda signum, frame: proc.send_signal(signum)) for s in STOPPING} \
        if in_main_thread else {}
    try:
        code = proc.wait()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    for thread in threads:
        thread.join()
    return code


def entry_point() -> int:
    """The `mvrecon` process (its console script, `python -m mvrecon.cli`): `main()`, and the pools' workers
    waited for before the interpreter exits."""
    code = main()
    wait_for_ended_pools()
    return code


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line (sys.argv by default) parsed, with `--mvrecon-args "--upright"` read as a value that starts
    with a dash (`commands._options.DASHED_VALUES`), which argparse alone refuses."""
    from .commands._options import DASHED_VALUES, join_option_value  # noqa: PLC0415 - numpy after one_blas_thread

    argv = sys.argv[1:] if argv is None else list(argv)
    for option in DASHED_VALUES:
        argv = join_option_value(argv, option)
    return build_parser(_command_in(argv)).parse_args(argv)


def _run(argv) -> int:
    args = parse_args(argv)
    _setup_logging(args.verbose + args.global_verbose, args.quiet or args.global_quiet)
    output = getattr(args, "output", None) if getattr(args._module, "HOLDS_OUTPUT", False) else None
    try:
        with hold_folder(output) if output else contextlib.nullcontext():
            code = int(args._module.run(args) or 0)
        sys.stdout.flush()  # here, where a reader that has gone is handled, not at the interpreter's exit
        return code
    except InputError as exc:
        clear_line()
        print(f"mvrecon: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except BrokenPipeError:  # `mvrecon ... | head`: the reader has gone, and nothing is left to say
        try:  # the exit's flush of stdout would raise again
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return 128 + signal.SIGPIPE
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            clear_line()
            print(f"mvrecon: error: {exc.filename or 'writing the outputs'}: no space left on the disk; "
                  f"{DiskFull.advice}", file=sys.stderr)
            return InputError.exit_code
        if not exc.filename:  # not about a path the user gave: a bug report needs the trace
            raise
        # an output path that is a file, an input that is a folder, a folder that cannot be written
        clear_line()
        print(f"mvrecon: error: {exc.filename}: {exc.strerror or exc}", file=sys.stderr)
        return InputError.exit_code
    except KeyboardInterrupt:
        return _interrupted(args._module)
    except Exception:
        if _interrupt.is_set():  # Ctrl-C inside a C extension's import surfaces as its own ImportError/RuntimeError
            return _interrupted(args._module)
        raise


if __name__ == "__main__":
    sys.exit(entry_point())
