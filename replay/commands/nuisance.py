"""The imaging nuisances of ``cathtrack simulate`` and ``cathtrack demo`` from their options."""

from __future__ import annotations

import argparse

from replay.simulation.render import ImagingNuisance


def nuisance_from_args(args: argparse.Namespace) -> ImagingNuisance:
    """The :class:`ImagingNuisance` of the options ``replay.cli._add_nuisance`` adds."""
    return ImagingNuisance(
        gain_flicker=args.gain_flicker,
        gain_drift=args.gain_drift,
        offset_gray=args.offset_gray,
        gamma_range=args.gamma_range,
        vibration_px=args.vibration_px,
        shift_px=tuple(args.camera_shift_px),
    )
