"""The run folder: a new one per run, ``run.json`` (what the run saw) and the report.

``run.json`` keeps the observer's samples, the medium's truth and the run's metadata, so
``netlab report DIR`` (`rebuild_report`) can write ``report.json`` and the plots again.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Mapping, Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

from netlab.errors import NetlabError
from netlab.pcap import read_run
from netlab.samples import Sample, agreement, connectivity
from netlab.truth import TruthState

RUN_JSON = "run.json"
RUN_SCHEMA = "netlab-scenario-run/1"


def new_run_dir(runs: Path, name: str) -> Path:
    """A new ``runs/<name>-<time>`` (``-2``, ``-3``... when taken)."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    base = Path(runs).absolute() / f"{name}-{stamp}"
    for n in itertools.count(1):
        path = base if n == 1 else base.with_name(f"{base.name}-{n}")
        try:
            path.mkdir(parents=True)
            return path
        except FileExistsError:
            continue
    raise AssertionError("unreachable")


def save_run(
    run_dir: Path, meta: Mapping[str, Any], samples: Sequence[Sample], truth: Sequence[TruthState]
) -> None:
    """Write ``run.json`` whole (a reader never sees half of it)."""
    data = {
        "schema": RUN_SCHEMA,
        "meta": meta,
        "samples": [s.to_json() for s in samples],
        "truth": [s.to_json() for s in truth],
    }
    tmp = run_dir / (RUN_JSON + ".tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    tmp.replace(run_dir / RUN_JSON)


def write_report(
    run_dir: Path,
    records: Any,
    samples: Sequence[Sample],
    truth: Sequence[TruthState],
    lag: float,
    meta: Mapping[str, Any],
    plots: bool = True,
) -> dict[str, Any]:
    """``report.json`` and (with `plots`) the plots from the captures' records and the
    observer's samples."""
    from netlab.report import write_report as write

    stats = agreement(samples, truth, lag=lag)
    return write(
        run_dir,
        records=records if records is not None else [],
        connectivity_samples=connectivity(samples, truth) if samples else None,
        agreement_samples=stats.per_sample or None,
        meta=meta,
        plots=plots,
    )


def rebuild_report(run_dir: Path) -> dict[str, Any]:
    """Write ``report.json`` and the plots of a run folder again, from its pcaps and (when a
    scenario run made it) its ``run.json``."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise NetlabError(f"no run folder {run_dir}")
    saved = run_dir / RUN_JSON
    pcaps = sorted(run_dir.glob("*.pcap"))
    if not saved.exists() and not pcaps:
        raise NetlabError(f"{run_dir} has neither captures (*.pcap) nor {RUN_JSON}")
    if not saved.exists():
        from netlab.report import write_report as write

        return write(run_dir, records=None)
    try:
        data = json.loads(saved.read_text())
        meta = dict(data["meta"])
        samples = [Sample.from_json(s) for s in data.get("samples", [])]
        truth = [TruthState.from_json(s) for s in data.get("truth", [])]
        lag = float(meta.get("agreement_lag_s") or 0.0)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise NetlabError(f"{saved} is not a scenario run's record: {exc}") from None
    records = read_run(run_dir) if pcaps else []
    return write_report(run_dir, records, samples, truth, lag, meta)
