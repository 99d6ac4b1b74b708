"""The ``exolan`` command line.

Each subcommand's arguments are declared here; its work lives in the module named by
``_HANDLERS`` (one concept, one home) and is imported only when the subcommand runs, so that
``exolan --version`` and ``exolan doctor`` stay fast.

Errors: every error a command raises ends here, in `main`, as one line on stderr, ``exolan COMMAND: what
(which file). Expected: what the inputs must be.``, and a non-zero exit status (2: the input or the
arguments, 1: anything else, 130: interrupted); never a traceback unless ``EXOLAN_DEBUG=1``.
"""
from __future__ import annotations

import argparse
import importlib
import os
import pickle
import platform
import re
import sys
import traceback

from . import __version__

def _at_least_one(text: str) -> int:
    """argparse type: an integer >= 1 (a count of seeds or fits), refused while the arguments are parsed."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}")
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n}")
    return n


# subcommand -> "module:function"; the function takes the parsed argparse.Namespace
_HANDLERS = {
    "doctor": "exolan.cli:doctor",
    "simulate": "exolan.world:cli_simulate",
    "plot": "exolan.plots:cli_plot",
    "train": "exolan.train:cli_train",
    "evaluate": "exolan.evaluate:cli_evaluate",
    "export": "exolan.export:cli_export",
    "rollout": "exolan.engine:cli_rollout",
    "reproduce": "exolan.reproduce:cli_reproduce",
    "diagnose": "exolan.diagnose:cli_diagnose",
    "pipeline": "exolan.pipeline:cli_pipeline",
}


# what each command reads: (argument dest, how the user names it, what it must be, a path that must exist);
# the existence of these paths is checked before the command runs, and an error names what they must be
_DATASET = "a dataset folder (layout 1) or recording <name>.csv (layout 2)"
_RUN = "a run folder written by `exolan train`"
_INPUTS = {
    "plot": [("trial_dir", "TRIAL_DIR", "a trial folder <root>/<SUBJECT>/<task>_k_m", True)],
    "train": [("data", "--data", _DATASET, True), ("config", "--config", "a TOML or JSON file of training settings", True)],
    "evaluate": [("run", "RUN", _RUN, True), ("data", "--data", _DATASET, True)],
    "export": [("run", "RUN", _RUN, True)],
    "rollout": [("model", "MODEL", "a weight file written by `exolan export`", True), ("data", "--data", _DATASET, True)],
    "reproduce": [("data", "--data", _DATASET, True),
                  ("ray", "--ray", "'local' (a fresh Ray instance on this machine) or the address of a running Ray "
                                   "cluster, e.g. HEAD:6379", False)],
    "diagnose": [("data", "DATA", _DATASET, True), ("model", "--model", "a DeLaN-based run folder written by `exolan train`", True)],
}
# what --out names, per command: a file or a folder (the rest)
_OUT_FILE = {"plot", "evaluate", "export", "rollout"}

# exceptions that mean "this input cannot be used" (exit 2); anything else is unexpected (exit 1)
_INPUT_ERRORS = (OSError, ValueError, EOFError, pickle.UnpicklingError)


class NotImplementedYet(SystemExit):
    pass


class _Parser(argparse.ArgumentParser):
    """argparse with its usage errors on one line: `exolan COMMAND: message (see exolan COMMAND --help)`."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: {_one_line(message)} (see `{self.prog} --help`)\n")


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _names(message: str, path: str) -> bool:
    """Whether the message names this path (as given or absolute), not merely contains its letters."""
    return any(re.search(r"(?<![\w.-])" + re.escape(p) + r"(?![\w-])", message) for p in (path, os.path.abspath(path)))


def _expected(command: str, args: argparse.Namespace, message: str) -> str:
    """`Expected: ...` for the inputs a message names (all of them when it names none) and --out."""
    given = [(label, str(getattr(args, dest)), what) for dest, label, what, _ in _INPUTS.get(command, [])
             if getattr(args, dest, None) is not None]
    out = getattr(args, "out", None)
    if out is not None:
        given.append(("--out", str(out), "a file in a folder that can be created and written" if command in _OUT_FILE
                      else "a folder that can be created and written"))
    named = [g for g in given if _names(message, g[1])]
    shown = named or given
    if not shown:
        return ""
    where = "" if named else " (while using " + ", ".join(f"{label} {value}" for label, value, _ in given) + ")"
    return where + ". Expected: " + "; ".join(f"{label} {what}" for label, _, what in shown)


def _error_line(command: str, args: argparse.Namespace, exc: BaseException) -> tuple[str, int]:
    """The one line (without the `exolan COMMAND: ` prefix) and the exit status for an exception."""
    if isinstance(exc, ImportError):
        how = "pip install 'exolan[ray]'" if exc.name == "ray" else "bash scripts/env.sh installs the pinned ones"
        return f"the Python package '{exc.name}' is not installed ({how})", 2
    if isinstance(exc, OSError) and exc.filename is not None:
        what = f"{exc.filename}: {exc.strerror or exc}"
        if getattr(exc, "filename2", None):
            what += f" ({exc.filename2})"
    else:
        what = _one_line(exc) or type(exc).__name__
    if isinstance(exc, _INPUT_ERRORS):
        return _one_line(what) + _expected(command, args, what), 2
    return (f"unexpected {type(exc).__name__}: {_one_line(what)}{_expected(command, args, what)}. If the inputs are "
            "as expected this is a bug: EXOLAN_DEBUG=1 shows the traceback"), 1


def _missing_input(command: str, args: argparse.Namespace) -> str | None:
    for dest, label, what, is_path in _INPUTS.get(command, []):
        value = getattr(args, dest, None)
        if is_path and value is not None and not os.path.exists(value):
            return f"{value}: no such file or directory. Expected: {label} {what}"
    return None


def doctor(args: argparse.Namespace) -> int:
    """Print the versions that must agree and the threads this machine offers."""
    import exolan

    print(f"exolan (python package) {exolan.__version__}")
    print(f"python                  {platform.python_version()} ({sys.executable})")
    try:
        import torch

        print(f"torch                   {torch.__version__} (threads: {torch.get_num_threads()}, "
              f"cuda: {torch.cuda.is_available()})")
    except ImportError:
        print("torch                   NOT INSTALLED")
    native = exolan.native_version
    print(f"exolan._native (Rust)   {native if native else 'NOT BUILT'}")
    print(f"cpu threads             {os.cpu_count()}")
    rt = exolan.RUNTIME
    print(f"runtime                 OMP_WAIT_POLICY={rt['omp_wait_policy']}, "
          f"allocator keeps freed memory: {'yes' if rt['malloc_keeps_freed_memory'] else 'no'}")
    ok = native is not None and native == exolan.__version__
    print("native build matches python package: " + ("yes" if ok else "NO"))
    return 0 if ok else 1


def _add_parsers(sub: argparse._SubParsersAction) -> None:
    sub.add_parser("doctor", help="versions of Python, torch, the native module and the crate")

    p = sub.add_parser("simulate", help="write a simulated exoskeleton world (layout 1)")
    p.add_argument("--out", required=True)
    p.add_argument("--users", type=int, default=21)
    p.add_argument("--tasks", default="all", help="'all', 'train' (the paper's 7) or comma-separated names")
    p.add_argument("--seconds", type=float, default=None, help="seconds per trial (default: per task)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--effect", action="append", default=[],
                   help="NAME:JOINT:VALUE[:SUBJECTS] (values comma-separated for multi-parameter effects, "
                        "subjects separated by '+'); repeatable")
    p.add_argument("--noise-free", action="store_true", help="no sensor noise (for physics checks)")

    p = sub.add_parser("plot", help="draw a trial (angles, moments, insole force) to a PNG")
    p.add_argument("trial_dir", help="<root>/<SUBJECT>/<task>_k_m directory")
    p.add_argument("--out", default=None)

    p = sub.add_parser("train", help="train a model (ExoLaN or a baseline)")
    p.add_argument("--data", default=None)
    p.add_argument("--method", default=None, help="exolan, delan-lstm, delan, mlp-tcn, mlp-lstm, mlp, tcn, lstm")
    p.add_argument("--no-lim", action="store_true")
    p.add_argument("--w-fd", type=float, default=None)
    p.add_argument("--w-ms", type=float, default=None)
    p.add_argument("--ms-norm", choices=["state", "increment"], default=None,
                   help="multi-step errors divided by the variance of q, q̇ (state, the paper's) or of their h-step "
                        "change (increment)")
    p.add_argument("--patience", type=int, default=None, help="early stopping: epochs without a better validation loss")
    p.add_argument("--val-users", type=int, default=None, help="training users carved out as the validation set")
    p.add_argument("--epochs", type=int, default=None)
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--config", default=None, help="TOML file; command-line flags override it")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda if available)")
    p.add_argument("--threads", type=int, default=None,
                   help="CPU threads of the run (default: one per core): the native training kernels take them all, "
                        "torch's own ops one (docs/TRAINING.md)")
    p.add_argument("--resume", action="store_true")
    p.add_argument("--out", required=True)

    p = sub.add_parser("evaluate", help="held-out torque and forward-dynamics errors of a run")
    p.add_argument("run")
    p.add_argument("--data", required=True)
    p.add_argument("--out", default=None, help="JSON file (default: RUN/evaluation.json)")

    p = sub.add_parser("export", help="export a trained run's weights (float64 safetensors) for the Rust engine")
    p.add_argument("run")
    p.add_argument("--out", required=True)

    p = sub.add_parser("rollout", help="open-loop rollouts of an exported model with the Rust engine")
    p.add_argument("model")
    p.add_argument("--data", required=True)
    p.add_argument("--horizon", type=int, default=20)
    p.add_argument("--out", default=None)

    p = sub.add_parser("reproduce", help="the paper's studies and report")
    p.add_argument("--scale", choices=["small", "converge", "medium", "paper"], default="small",
                   help="small: the main job's (minutes); converge: the claims, early-stopped, 3 seeds (~2 h on 2 cores)")
    p.add_argument("--data", default=None)
    p.add_argument("--out", required=True)
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--ray", default=None, metavar="ADDRESS")

    p = sub.add_parser("diagnose", help="find what the model's physics gets wrong, extend it, measure the gain")
    p.add_argument("data")
    p.add_argument("--model", default=None, help="a trained DeLaN-based run (default: fit a slow-context base here)")
    p.add_argument("--out", required=True)
    p.add_argument("--quick", action="store_true", help="short fits and fewer bootstrap draws (minutes, not tens)")
    p.add_argument("--effects", default=None, help="comma-separated candidate effects to test (default: all)")
    p.add_argument("--joints", default=None, help="comma-separated joint names to test (default: all)")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--unweighted", action="store_true",
                   help="refit and decide without the per-trial misfit weights (ordinary least squares; see "
                        "exolan.diagnose.fit)")
    p.add_argument("--no-pelvis-surge", action="store_true",
                   help="leave out the base term for the pelvis's fore-aft acceleration (estimated from both insoles)")
    p.add_argument("--no-lim-cop", action="store_true",
                   help="the base's insole mapping sees only the joint angles, B(q, z), not the centre of pressure")
    p.add_argument("--no-adapt-model", action="store_true",
                   help="with --model: judge the run's networks at their pooled context as given, without fitting "
                        "them to the data's training segments first")
    p.add_argument("--pelvis-tilt", action="store_true",
                   help="add the optional pelvis-tilt base term (the other hip's angle as a coordinate shift)")
    p.add_argument("--computed-gain-limit", action="store_true",
                   help="(the default now; kept for old scripts) the gain's detection limit computed at the base's misfit")
    p.add_argument("--measured-gain-limit", action="store_true",
                   help="also measure the exo torque gain's detection limit by writing a known gain into the data "
                        "(one or two more base fits)")
    p.add_argument("--learned-only", action="store_true",
                   help="skip the physics-first identification against a parametric rigid-body base; size the terms "
                        "jointly with the learned base only")
    p.add_argument("--no-rescue", action="store_true",
                   help="do not try a further term (in forward selection) or the extended model paired over seeds "
                        "where its cross-seed comparison fails (and no --rescue-frictions)")
    p.add_argument("--rescue-frictions", action="store_true",
                   help="on the learned path, fit a friction from scratch where its warm refit fails the gain rules "
                        "(the base may have absorbed it), paired over seeds: up to 13 more base fits (off by default: "
                        "physics first sizes absorbed dissipation where its parametric base is adequate)")
    p.add_argument("--optima", type=_at_least_one, default=None, metavar="N",
                   help="term-free fits from scratch at N other seeds that measure the noise between optima, against "
                        "which every fit from scratch is judged (default 2; at least 1: the noise needs a twin)")
    p.add_argument("--paired-seeds", type=_at_least_one, default=None, metavar="N",
                   help="a rescued friction is fitted from scratch at N other seeds too, each compared with the "
                        "term-free fit of its seed (default 4: five seeds in all; at least 1: a spread needs two seeds)")
    p.add_argument("--workers", type=_at_least_one, default=None, metavar="N", dest="fit_workers",
                   help="independent fits (candidates, seeds) side by side on N threads, each torch at one thread; "
                        "the same results as one at a time (default: the cores, at most 4)")
    p.add_argument("--measured-delay-limit", action="store_true",
                   help="also measure the actuation delay's detection limit by writing a known delay into the data "
                        "(in the gain's injection fit; confounded where the data hold a delay already)")

    p = sub.add_parser("pipeline", help="the main job: simulate, train, evaluate, export, rollout, diagnose, report")
    p.add_argument("--out", default="out/main")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="exolan", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"exolan {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_parsers(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    command = args.command
    module_name, func_name = _HANDLERS[command].split(":")
    try:
        module = importlib.import_module(module_name)
        handler = getattr(module, func_name)
    except (ImportError, AttributeError) as exc:
        if not (isinstance(exc, ImportError) and exc.name not in (module_name, None)):
            print(f"exolan {command}: not implemented yet", file=sys.stderr)
            return 3
        line, rc = _error_line(command, args, exc)  # a dependency of the command's module is missing
        print(f"exolan {command}: {line}", file=sys.stderr)
        return rc
    missing = _missing_input(command, args)
    if missing:
        print(f"exolan {command}: {missing}", file=sys.stderr)
        return 2
    try:
        rc = handler(args)
    except KeyboardInterrupt:
        print(f"exolan {command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the one place where a command's errors become one line
        if os.environ.get("EXOLAN_DEBUG", "") not in ("", "0"):
            traceback.print_exc()
        line, rc = _error_line(command, args, exc)
        print(f"exolan {command}: {line}", file=sys.stderr)
        return rc
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
