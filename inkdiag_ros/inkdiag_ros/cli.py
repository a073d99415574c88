"""``inkdiag``: the command line, one entry point with a subcommand per task.

    inkdiag calibrate HEALTHY --nominal NOMINAL.yaml --out HEAD.yaml
    inkdiag train --profile HEAD.yaml --out MODEL.joblib [--features ...] [--baseline] [--data LABELLED]
    inkdiag baseline RECORDING --profile HEAD.yaml --out B.npz [--frames N] [--min-frames N] [--fm-frames N]
                     [--max-abs-v V] [--topic T]
    inkdiag label RECORDING --model MODEL.joblib [--baselines B.npz] --out LABELS.csv
    inkdiag estimate RECORDING --profile HEAD.yaml [--rows ...] --out FM.csv
    inkdiag record BAG_DIR --namespace /head_00 [--topics ...] [--duration S]
    inkdiag replay BAG_DIR [--rate R | --as-fast-as-possible] [--namespace NS] [--topics ...] [--loop]
    inkdiag printer --heads N [--processes P] [--model M] [--baselines PATTERN] [--simulate] [--duration S]

A RECORDING is an .npz file or a rosbag2 bag directory (see docs/bags.md).

Each subcommand is a module of :mod:`inkdiag_ros.verbs` with ``HELP`` (one
line), ``DESCRIPTION``, ``add_arguments(parser)``, ``run(args) -> int`` and optionally
``MAKES_OUT_DIR`` (True: ``run`` creates its ``--out``'s directory), ``OUT_STDOUT``
(True: ``--out -`` is standard output; elsewhere ``-`` is refused), ``REPLACES_OUT`` (True: ``run``
writes a file beside ``--out`` and renames it over ``--out``, so a device, pipe or socket there is refused) and
``extra_outputs(args)`` (the files ``run`` writes beside ``--out``, never over an input); the
modules import the core only inside ``run``, so ``--help`` is fast. Bad input
(a missing file, another schema, a recording of another sampling, a profile
calibration cannot fit, an ``--out`` in no writable directory) is one line on stderr,
``inkdiag VERB: error: ...``, and exit status 2, checked before any work where it can be;
so are argparse's own usage errors. A reader of the output that stops early (``| head``) is
one line too, exit status 1.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import re
import sys
import tempfile
from pathlib import Path

__all__ = ["INPUT_ARGS", "VERBS", "build_parser", "main"]

INPUT_ARGS = ("recording", "healthy", "model", "baselines", "profile", "nominal", "data", "blocked", "blocked_labels",
              "empty", "labels")
RECORDING_ARGS = ("recording", "healthy", "data", "blocked", "empty")  # inputs that may be a bag directory
"""The verbs' arguments that name files they read: an ``--out`` that is one of them is refused."""

VERBS = ("calibrate", "train", "baseline", "label", "estimate", "record", "replay", "printer")
"""The subcommands, in the order ``inkdiag --help`` lists them."""


class OneLineParser(argparse.ArgumentParser):
    """argparse's parser with its usage errors on one line (``inkdiag VERB: error: ...``), status 2 (also
    ``inkdiag_echo``'s)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The ``inkdiag`` parser with one subparser per verb."""
    parser = OneLineParser(
        prog="inkdiag", description="inkdiag: fault detection, isolation and estimation for piezo inkjet "
        "printheads. Offline tasks on a head profile and recordings; see docs/cli.md.")
    sub = parser.add_subparsers(dest="verb", metavar="VERB", required=True)
    for verb in VERBS:
        module = importlib.import_module(f"{__package__}.verbs.{verb}")
        p = sub.add_parser(verb, help=module.HELP, description=module.DESCRIPTION,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(p)
        p.set_defaults(_run=module.run, _makes_out_dir=getattr(module, "MAKES_OUT_DIR", False),
                       _out_stdout=getattr(module, "OUT_STDOUT", False),
                       _replaces_out=getattr(module, "REPLACES_OUT", False),
                       _extra_outputs=getattr(module, "extra_outputs", None), _parser=p)
    return parser


def main(argv=None) -> int:
    """Run ``inkdiag``; returns the exit status (0 done, 1 failed, or its output's reader gone, 2 bad input,
    130 interrupted)."""
    words = sys.argv[1:] if argv is None else list(argv)
    if words[:1] in (["record"], ["replay"]):  # they run until stopped: a shell's background job starts with SIGINT
        import signal  # ignored, and a Ctrl-C while importing was lost (helper-123); their node takes it once up

        if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
            signal.signal(signal.SIGINT, signal.default_int_handler)  # 'interrupted', 130, as in a terminal
    if words[:1] == ["printer"]:  # a printer stopped at any time is status 0 (docs/scaling.md), also while it
        from ._launch import stop_means_exit_0  # imports (seconds) and starts its children: not 143 or 130

        with stop_means_exit_0():
            return _main(argv)
    try:
        return _main(argv)
    except Exception as exc:  # a Ctrl-C in a C extension's init (rclpy's) comes out as an ImportError it caused
        from ._launch import in_chain

        if not in_chain(exc, KeyboardInterrupt):
            raise
    except KeyboardInterrupt:  # Ctrl-C while it imports (seconds, before _main's own handling): one line too
        pass
    verb = f" {words[0]}" if words[:1] and words[0] in VERBS else ""
    print(f"inkdiag{verb}: interrupted", file=sys.stderr)
    return 130


#: Options whose value may start with "-" (argparse takes "--rows -3:-1" for an option without its value).
_DASH_VALUES = ("--rows",)


def _main(argv) -> int:
    words = list(sys.argv[1:] if argv is None else argv)
    for i in range(len(words) - 2, -1, -1):  # "--rows -3:-1" as "--rows=-3:-1": its own error names the value
        if words[i] in _DASH_VALUES and re.match(r"-[0-9:]", words[i + 1]):  # not an option ("--rows --out x")
            words[i:i + 2] = [f"{words[i]}={words[i + 1]}"]
    args, extra = build_parser().parse_known_args(words)
    if extra:  # said by the verb's parser: "inkdiag VERB: error: ...", as every other usage error
        args._parser.error(f"unrecognized arguments: {' '.join(extra)}")
    from inkdiag_core.checks import InputError

    try:
        _check_out(args)
        status = int(args._run(args) or 0)
        if sys.stdout is not None:
            sys.stdout.flush()  # here, not at exit: a reader that stopped early is said like any other error
        return status
    except KeyboardInterrupt:
        print(f"inkdiag {args.verb}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError as exc:  # a reader that stopped early (`| head`), or an --out pipe's
        if sys.stdout is not None:  # what is left in stdout's buffer goes nowhere, not to a traceback at exit
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        print(f"inkdiag {args.verb}: error: its output's reader is gone ({exc.strerror})", file=sys.stderr)
        return 1
    except (InputError, ValueError, OSError) as exc:  # bad input: one line, status 2
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        out = getattr(args, "out", None)
        if isinstance(exc, OSError) and out and out != "-" and (
                (exc.filename is None and exc.errno in _WRITE_ERRNOS)  # a full disk says no file name
                or _is_out_or_beside(exc.filename, out)):
            msg = f"--out {out}: {exc.strerror or msg}"
        print(f"inkdiag {args.verb}: error: {msg}", file=sys.stderr)
        return 2


#: Errors only writing raises (a full disk or quota, a file too large, a read-only file system).
_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS})


def _is_out_or_beside(filename, out: str) -> bool:
    """``filename`` (an OSError's) is ``out``, its temporary file beside it (``OUT.xxxx.tmp``,
    ``_fileio.temp_beside``) or a directory on the way to it (``train`` makes them)."""
    if not filename or not isinstance(filename, (str, os.PathLike)):
        return False
    f, o = Path(filename).resolve(), Path(out).resolve()
    return (f == o or (f.parent == o.parent and f.name.startswith(o.name + ".") and f.name.endswith(".tmp"))
            or (f in o.parents and not f.exists()))


def _same_path(a: str, b: str) -> bool:
    """The same file (a hard link or symlink too) or, where one does not exist yet, the same resolved path."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist
        return Path(a).resolve() == Path(b).resolve()


def _check_out(args) -> None:
    """A verb's ``--out`` must go into an existing, writable directory (not for a verb whose module sets
    ``MAKES_OUT_DIR``: it creates the directory) and must not be one of its inputs: said before any work is done."""
    out = getattr(args, "out", None)
    if out == "":  # open('') says "[Errno 2] No such file or directory: ''"
        raise OSError("--out is empty: give the output file's name")
    if out == "-" and not args._out_stdout:
        raise OSError(f"--out -: inkdiag {args.verb} writes a file, not standard output: give the file's name")
    if out == "-" and sys.stdout is None:
        raise OSError("--out -: standard output is closed")
    if out and out != "-":
        inputs = [(name, getattr(args, name, None)) for name in INPUT_ARGS]
        if getattr(args, "model", None):  # the model's manifest is read with it
            from inkdiag_core.persistence import manifest_path

            inputs.append(("model", str(manifest_path(args.model))))
        extra_outputs = getattr(args, "_extra_outputs", None)  # a manifest, a fit report, written beside --out
        outs = [out] + ([str(o) for o in extra_outputs(args)] if extra_outputs else [])
        for name, value in inputs:
            what = name.upper() if name in ("recording", "healthy") else "--" + name.replace("_", "-")
            for o in outs:
                if value and _same_path(value, o):
                    extra = "'s manifest" if value != getattr(args, name, None) else ""
                    if o == out:
                        raise OSError(f"--out {out} is also the {what} input{extra}: writing it would destroy that "
                                      "input")
                    raise OSError(f"--out {out} writes {o}, which is also the {what} input{extra}: it would be "
                                  f"written over the {what} input")
            inside = [o for o in outs if value and name in RECORDING_ARGS and Path(value).is_dir()
                      and Path(value).resolve() in Path(o).resolve().parents]
            if inside:
                kind = "a bag directory" if (Path(value) / "metadata.yaml").is_file() else "a directory"
                what_out = f"--out {out}" if inside[0] == out else f"--out {out} writes {inside[0]}, which"
                raise OSError(f"{what_out} is inside the {what} input {value} ({kind}): writing there "
                              "would change or destroy the recording; write it elsewhere")
        if Path(out).is_dir() and not args._makes_out_dir:
            raise OSError(f"--out {out} is a directory; give the output file's name")
        if args._replaces_out:
            from inkdiag_core import refuse_to_replace

            for o in outs:
                try:
                    refuse_to_replace(o)
                except OSError as exc:
                    raise OSError(f"--out {exc}" if o == out else f"--out {out}: beside it, {exc}") from None
    if out and out != "-":
        parent = Path(out).parent
        if not args._makes_out_dir:
            if not parent.is_dir():
                raise OSError(f"{parent}: no such directory for --out")
            if not os.access(parent, os.W_OK):
                raise OSError(f"{parent}: not writable, for --out")
        while not parent.exists() and parent != parent.parent:  # the verb makes the rest of the way
            parent = parent.parent
        try:  # what access() does not tell (root, a read-only mount, /sys, /proc): a file made there and removed;
            if not os.path.exists(out) or os.path.isfile(out):  # not for a FIFO, /dev/fd/N: opened as they are
                tempfile.TemporaryFile(dir=parent).close()
        except OSError as exc:
            raise OSError(f"--out {out}: its directory {parent} takes no new file ({exc.strerror or exc})") from None


if __name__ == "__main__":
    sys.exit(main())
