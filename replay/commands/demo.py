"""``cathtrack demo``: the live loop on an embedded simulated rig (:mod:`replay.demo`)."""

from __future__ import annotations

import argparse

from replay.commands.nuisance import nuisance_from_args
from replay.demo import DemoSettings, run_demo


def run(args: argparse.Namespace) -> int:
    settings = DemoSettings(
        seconds=args.seconds,
        frame_rate_hz=args.frame_rate_hz,
        seed=args.seed,
        estimator=args.estimator,
        images=not args.no_images,
        image_every=args.image_every,
        image_noise_gray=args.image_noise_gray,
        image_nuisance=nuisance_from_args(args),
        keep_awake=not args.no_keep_awake,
        segmentation_worker=not args.no_segmentation_worker,
        realtime=not args.no_realtime,
    )
    return run_demo(settings, args)
