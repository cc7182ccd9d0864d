"""The results store: one JSON record per (method, subject, protocol, clip, seed, config).

Every number in a table is read from a record, and every record says how it was made
(the lm-evaluation-harness results file; nerfbaselines' results that carry what produced
them). Tables and charts (:mod:`lmgs_eval.report`) are pure
functions of these files; ``lmgs-eval verify`` re-hashes the artefacts they reference.

Schema version ``2`` (``SCHEMA_VERSION``; version 1 records are migrated on read,
:mod:`~lmgs_eval.results.migrate`). The typed form is :class:`~lmgs_eval.results.types.Record`,
each part of which checks its fields when it is made (a record read, or built by the runner, is
checked once, there; :func:`validate` lists what does not fit in a JSON form); the store hands out
typed records (:func:`load_records`, :func:`iter_store`, :func:`find_record`), the runner writes
them, and tables and report read their attributes. :func:`frame` gives a store as a pandas
DataFrame. ``?`` marks an optional field; ``|null`` a field that may be null.

=================  ======================================================================
Field              Meaning
=================  ======================================================================
schema_version     ``"2"``
method             ``name`` (registry name), ``display_name`` (as printed), ``family``
                   (``2D``/``NeRF``/``3DGS``/``external``/``ground-truth``/``control``),
                   ``description`` (what was kept / simplified), ``standins`` [str],
                   ``variant``? (str|null: ablation / sweep variant of a base method,
                   e.g. ``theta0.4``; such rows go to Tables III/IV, not Table I),
                   ``control``? ({kind, targets [metric keys]}: a calibration control and
                   the metrics it is a negative control for), ``components``? ({part:
                   setting}: the switchable parts the method declares, e.g. lmgs's
                   ``se``, ``lc``, ``gr``, ``theta``, ``se_cap``; Table III/IV rows are
                   labelled from these)
subject            ``name``, ``bundled`` (bool), ``standin`` (str|null: what it stands in
                   for, e.g. "synthetic head"), ``frames``, ``width``, ``height``
                   (int|null), ``path`` (str|null), ``sha256`` (subject manifest, str|null)
protocol           ``name`` (``self``/``cross``/``stress``/``calibration``/``capacity``),
                   ``version``, ``clip`` (test split, driving clip "A"/"B", or the stress
                   condition), ``split`` (str|null), ``n_frames`` (int|null)
metrics            ``{key: entry}``; keys are canonical (``psnr``, ``ssim``, ``lpips``,
                   ``lpips_custom`` (LPIPS alex on a trunk that is not torchvision's),
                   ``lmd``, ``lse_d``, ``lse_c``...); entry: ``value`` (float|null),
                   ``n_original``, ``n_effective``, ``higher_is_better``, ``unit``,
                   ``backend`` (what made the number: ``stlpips-alex``, ``lpips-alex``,
                   ``onnxruntime:bundled-sync``...; numbers of different backends never
                   share a column silently), ``backend_version``, ``weights_sha256``
                   (str|null), ``flags`` [str], ``standin`` (str|null), ``per_item``
                   ([float|null] per frame / window, rounded to 6 significant digits, or
                   null), ``values``? (every number the metric reported),
                   ``weights_files``? ({role: {path, sha256}}: each weights file when
                   ``weights_sha256`` is a hash over several)
cost               ``train_seconds``, ``fps``, ``ms_per_frame`` {audio, network, raster,
                   total}, ``first_frame_ms``, ``realtime_factor``, ``n_params``,
                   ``n_gaussians``, ``model_mb``, ``peak_mb`` (all number|null),
                   ``device`` (str|null)
config             the method's full configuration (object)
config_hash        short hash of ``config`` (the method's own, or :func:`config_hash`)
seed               int
code               ``version``, ``git_commit`` (str|null), ``dirty`` (bool|null)
machine            ``cpu``, ``threads``, ``torch`` (str|null), ``cuda_device`` (str|null),
                   ``platform``
artefacts          ``{role: {path, sha256}}`` (renders, gt, checkpoint, metric weights);
                   a relative path is relative to the store root
status?            ``{state: "ok"|"failed", reason: str|null}`` (absent means ok)
run?               structured facts of the run: ``se_fraction``? (share of face points
                   Spatial Enhancement selected, 0..1), ``budget``? ({density,
                   preset_density}: the subject's own Gaussian density the method took)
created            ISO 8601 time of writing
notes              [str]
=================  ======================================================================
"""

from lmgs.fileio import sha256_file  # the one file hash, part of this package's API
from lmgs_eval.results.dataframe import frame
from lmgs_eval.results.migrate import migrate
from lmgs_eval.results.notes import BUDGET_NOTE, SE_NOTE, budget_note, se_note
from lmgs_eval.results.provenance import (EMPTY_COST, compact, config_hash, git_info, machine_info, make_record,
                                          metric_entries, now_iso)
from lmgs_eval.results.schema import FAMILIES, PROTOCOLS, READ_VERSIONS, SCHEMA_VERSION, check, validate
from lmgs_eval.results.store import (IMPORTED_FILE, MADE_ELSEWHERE, check_artefacts, copy_records, find_finished, find_record,
                                     imported_records, iter_store, load_records, package_file, record_path,
                                     resolve_artefact, run_path, se_fraction, snapshot_records, subject_dir, to_record,
                                     write_record)
from lmgs_eval.results.types import Record, replace

__all__ = [
    "BUDGET_NOTE", "EMPTY_COST", "FAMILIES", "IMPORTED_FILE", "MADE_ELSEWHERE", "PROTOCOLS", "READ_VERSIONS", "Record",
    "SCHEMA_VERSION", "SE_NOTE", "budget_note", "check", "check_artefacts", "compact", "config_hash", "copy_records",
    "find_finished", "find_record", "frame", "git_info", "imported_records", "iter_store", "load_records",
    "machine_info", "make_record", "metric_entries", "migrate", "now_iso", "package_file", "record_path", "replace",
    "resolve_artefact", "run_path", "se_fraction", "se_note", "sha256_file", "snapshot_records", "subject_dir", "to_record", "validate",
    "write_record",
]
