"""Run estimators over recordings and summarise their accuracy (``cathtrack evaluate``).

A recording (tracker.io.recording) is replayed through the same pipeline as the live loop --
frames, optional segmentation of the images, reconstruction, every estimator -- and each
method's bending-plane error (the wrapped difference between estimated and true
``delta_1 = q_r + delta_L``, which is the difference of the delta_L) is summarised as in the
paper: RMS and maximum over all configurations, per bending plane, against tip deflection and
against segmentation noise, next to the per-frame Cramer-Rao bound of the tip. For the UKF the
NEES against its chi-square band and the coverage of the +/-2 sigma interval say whether its
uncertainty is honest.

- :mod:`.run`: running methods over observations; :func:`replay_recording` and :class:`Replay`;
- :mod:`.tables`: statistics per group of frames (:func:`replay_tables`; how continuous labels
  are binned), the paper's checks, the markdown report;
- :mod:`.outputs`: CSV, figures and the rerun file; :func:`evaluate_recording`;
- :mod:`.batch`: many recordings on a process pool or a Dask cluster (:func:`evaluate_batch`).
"""

from replay.evaluation.batch import BatchItem, evaluate_batch, write_batch
from replay.evaluation.outputs import (
    CSV_COLUMNS,
    EvaluationOutput,
    evaluate_recording,
    write_figures,
    write_frames_csv,
    write_rrd,
    write_tables_csv,
)
from replay.evaluation.run import (
    METHOD_ORDER,
    SOURCES,
    MethodResult,
    Replay,
    default_methods,
    recording_scene,
    replay_recording,
    run_methods,
)
from replay.evaluation.tables import (
    BOUND_NAME,
    DEFLECTION_BIN_EDGES_MM,
    LEVELS_MAX,
    NOISE_BIN_EDGES,
    TABLES,
    Check,
    Group,
    bin_names,
    group_frames,
    markdown_table,
    paper_checks,
    replay_markdown,
    replay_tables,
)

__all__ = [
    "BOUND_NAME",
    "CSV_COLUMNS",
    "DEFLECTION_BIN_EDGES_MM",
    "LEVELS_MAX",
    "METHOD_ORDER",
    "NOISE_BIN_EDGES",
    "SOURCES",
    "TABLES",
    "BatchItem",
    "Check",
    "EvaluationOutput",
    "Group",
    "MethodResult",
    "Replay",
    "bin_names",
    "default_methods",
    "evaluate_batch",
    "evaluate_recording",
    "group_frames",
    "markdown_table",
    "paper_checks",
    "recording_scene",
    "replay_markdown",
    "replay_recording",
    "replay_tables",
    "run_methods",
    "write_batch",
    "write_figures",
    "write_frames_csv",
    "write_rrd",
    "write_tables_csv",
]
