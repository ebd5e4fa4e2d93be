"""The lab's set-up commands: ``fit-model``, ``register`` and ``import`` (docs/setup.md).

Each command has an ``add_*_parser(subparsers)`` that declares its options and a
``run_*(args)`` that does the work (in :mod:`replay.commands.fit_model`,
:mod:`replay.commands.register` and :mod:`replay.commands.import_logs`) and prints the result.
Errors a user can cause raise a ValueError or OSError with one line naming the file;
``replay.cli.main`` prints it and exits with code 2.
"""

from __future__ import annotations

import argparse
from importlib import import_module

CONVENTION = (
    "delta_L = 0 during the routine: x_b is the proximal bending direction at q_r = 0"
    " (catheter body straight and untwisted)"
)
"""How ``register`` fixes the rotation about z_b, which delta_L cannot be told apart from
(models/registration.py)."""


# The commands' modules are imported when a command runs: this module is imported to build
# the parser of every cathtrack command, and the models, the table readers and scipy would
# add about 0.25 s to the start of each (as replay.cli does for its own commands).
def run_fit_model(args: argparse.Namespace) -> int:
    return import_module("replay.commands.fit_model").run(args)


def run_register(args: argparse.Namespace) -> int:
    return import_module("replay.commands.register").run(args)


def run_import(args: argparse.Namespace) -> int:
    return import_module("replay.commands.import_logs").run(args)


def add_fit_model_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "fit-model",
        help="fit the catheter model's modal matrices to measured shapes",
        description=(
            "Fit the modal matrices A of both segments to measured shapes (docs/setup.md): "
            "backbone points in the base frame or tangent angles at known arclengths, in a "
            "CSV or MATLAB .mat table. Prints the RMS residuals per segment and overall (mm "
            "and deg), in-sample and cross-validated on held-out configurations; writes the "
            "model file (docs/model-file.md) and a figure of measured against fitted shapes."
        ),
    )
    p.add_argument("shapes", metavar="SHAPES", help="measured shapes (.csv or .mat)")
    p.add_argument("--out", default="model.toml", metavar="FILE", help="model file (model.toml)")
    p.add_argument(
        "--template",
        metavar="FILE",
        help="model whose segment lengths, delta_2 and markers the fit keeps (default model)",
    )
    p.add_argument(
        "--psi-size",
        type=int,
        nargs="+",
        metavar="N",
        help="arclength basis size, for both segments or proximal and distal (3)",
    )
    p.add_argument(
        "--eta-size",
        type=int,
        nargs="+",
        metavar="M",
        help="joint basis size, for both segments or proximal and distal (3)",
    )
    p.add_argument(
        "--folds", type=int, default=5, help="cross-validation folds (5; 0: no cross-validation)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the folds' shuffle (0)")
    p.add_argument(
        "--figure", metavar="FILE", help="figure of the fit (default: the model file's .png)"
    )
    p.add_argument("--no-figure", action="store_true", help="do not write the figure")
    p.set_defaults(run=run_fit_model)
    return p


def add_register_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "register",
        help="register the catheter base in the world frame from a routine seen by the rig",
        description=(
            "Without OBSERVATIONS: print the registration routine (joint configurations to "
            "step through; --routine-out writes it as CSV). With OBSERVATIONS (a table of "
            "joint values and segmented points per image pair, or a recording): estimate the "
            "pose of the catheter base {B} in the world frame, report the residuals and the "
            "pose's uncertainty, and write it into the rig file's [base] table. Convention: "
            + CONVENTION
            + "."
        ),
    )
    p.add_argument(
        "observations",
        nargs="?",
        metavar="OBSERVATIONS",
        help="the routine's observations: .csv or .mat table, or a recording (.mcap)",
    )
    p.add_argument("--rig", metavar="FILE", help="rig file of the calibrated cameras")
    p.add_argument(
        "--rig-model",
        choices=["pinhole", "orthographic"],
        default="pinhole",
        help="the rig's cameras (default) or the orthographic planes (points in mm)",
    )
    p.add_argument("--model", metavar="FILE", help="catheter model file (default model)")
    p.add_argument(
        "--out", metavar="FILE", help="rig file to write (default: update --rig in place)"
    )
    routine = p.add_argument_group("routine")
    routine.add_argument("--routine-out", metavar="FILE", help="write the routine (CSV)")
    routine.add_argument(
        "--planes", type=int, default=4, help="bending planes, q_r in equal steps (4)"
    )
    routine.add_argument(
        "--bends-mm",
        type=float,
        nargs="+",
        metavar="MM",
        help="(q_p, q_d) pairs bent in every plane (default 0.5 0 0.8 0.8)",
    )
    p.set_defaults(run=run_register)
    return p


def add_import_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "import",
        help="turn the lab's logs (CSV or .mat) into a recording",
        description=(
            "Read the lab's logs -- joint samples with times, the segmented points of each "
            "view with times, optionally the ground truth -- as a mapping file (TOML, "
            "docs/setup.md) names them, and write a recording (MCAP, docs/recording.md) with "
            "the model and the registered rig, ready for 'cathtrack evaluate' and "
            "'cathtrack track --recording'."
        ),
    )
    p.add_argument("mapping", metavar="MAPPING", help="mapping file (TOML)")
    p.add_argument(
        "--rig", required=True, metavar="FILE", help="rig file with the registered [base]"
    )
    p.add_argument("--model", metavar="FILE", help="catheter model file (default model)")
    p.add_argument("--out", default="recording.mcap", metavar="FILE", help="recording to write")
    p.set_defaults(run=run_import)
    return p
