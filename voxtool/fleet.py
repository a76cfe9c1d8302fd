"""Fleets: one command over many sources (`voxtool stats logs/*.mcap --workers 4`), one task per
source on a Dask cluster (in this process, one after the other, without one). A bad source
gets its one-line error in its row; the others still finish and are written."""

from __future__ import annotations

import time
from pathlib import Path

from voxtool.errors import ParameterError, VoxtoolError

ADDITIVE = ("scans", "points", "points_dropped", "voxel_updates", "occupied_voxels", "free_voxels", "packets", "bytes",
            "changed_voxels", "raw_bytes")
SUFFIX = {"build": ".vxm", "encode": ".mcap"}


def output_names(sources: list[Path], out_dir: Path, command: str) -> list[Path]:
    """The output of each source in `out_dir`: named after the source by the shortest suffix of
    its path that tells the sources apart (sources.source_names: data/kaist03/pcd and
    data/norlab/pcd give kaist03-pcd and norlab-pcd); a source given twice, or an output that is
    a source, is refused."""
    from voxtool.sources import source_names

    outs = [out_dir / f"{name}{SUFFIX[command]}" for name in source_names(sources)]
    seen: dict[Path, Path] = {}
    inputs = {s.resolve() for s in sources}
    for s, o in zip(sources, outs):
        if o in seen:
            raise ParameterError(f"{s}: its output {o} would also be {seen[o]}'s: give sources distinct names")
        if o.resolve() in inputs:
            raise ParameterError(f"{o}: the output would overwrite a source")
        seen[o] = s
    return outs


def run_one(command: str, source: str, output: str | None, job: dict) -> dict:
    """One source's row (a Dask task): its result, or its error and exit code."""
    from voxtool import api

    row = {"source": source, "output": output, "exit_code": 0, "error": None, "warnings": []}
    try:
        if command == "build":
            result = api.build_map(source, job["options"], job["params"], job["sensor"], job["backend"], output,
                                   False, dict(job["backend_options"]))
        elif command == "encode":
            result = api.encode_log(source, output, job["options"], job["params"], job["sensor"], job["backend"],
                                    dict(job["backend_options"]), job["encode"], False)
        else:
            result = api.any_stats(source)
        row["warnings"] = api.dropped_warnings(source, result)
        row["result"] = result
    except VoxtoolError as err:
        row.update(exit_code=err.exit_code, error=str(err), output=None)
    except MemoryError:
        row.update(exit_code=1, error=f"{source}: out of memory", output=None)
    return row


def run_fleet(command: str, sources: list[Path], job: dict, out_dir: Path | None = None, client=None,
              progress: bool | None = None, outputs: list[Path] | None = None) -> dict:
    """Every source's row and the totals; the CLI exits with the first failed row's code.
    `outputs`: output_names' answer, when the caller has it already."""
    from voxtool.progress import track

    t0 = time.perf_counter()
    if outputs is None:
        outputs = output_names(sources, out_dir, command) if out_dir is not None else [None] * len(sources)
    args = [(command, str(s), str(o) if o is not None else None, job) for s, o in zip(sources, outputs)]
    if client is None:
        rows = [run_one(*a) for a in track(args, len(args), command, progress, "source")]
    else:
        from voxtool.cluster import gather_all

        futures = [client.submit(run_one, *a, pure=False) for a in args]
        rows = gather_all(client, futures, command, progress)
    ok = [r for r in rows if r["exit_code"] == 0]
    totals = {"sources": len(rows), "ok": len(ok), "failed": len(rows) - len(ok),
              "wall_s": round(time.perf_counter() - t0, 6)}
    for key in ADDITIVE:
        values = [r["result"][key] for r in ok if isinstance(r["result"].get(key), int)]
        if values:
            totals[key] = sum(values)
    return {"command": command, "rows": rows, "totals": totals}


def fleet_job(options, params, sensor, backend: str, backend_options: dict, **more) -> dict:
    """What every task of a build or encode fleet needs (pickled to the workers)."""
    return {"options": options, "params": params, "sensor": sensor, "backend": backend,
            "backend_options": backend_options, **more}


def run_fleet_on(command: str, sources: list[Path], job: dict, out_dir: Path | None, workers: int | None,
                 scheduler: str | None, progress: bool | None = None, outputs: list[Path] | None = None) -> dict:
    """run_fleet on a Dask cluster when --workers or --scheduler asks for one, else here; the
    output directory is made, and clashing output names refused, before any cluster starts.
    `outputs` names the outputs instead of `out_dir` (one source written to the file given)."""
    from voxtool.cluster import wanted

    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        outputs = output_names(sources, out_dir, command)
    if not wanted(workers, scheduler):
        return run_fleet(command, sources, job, out_dir, None, progress, outputs)
    from voxtool.cluster import dask_client

    with dask_client(workers, scheduler) as client:
        return run_fleet(command, sources, job, out_dir, client, progress, outputs)


def first_failure(report: dict) -> VoxtoolError | None:
    """The error the command exits with: the first failed source's (its code), naming how many failed."""
    failed = [r for r in report["rows"] if r["exit_code"]]
    if not failed:
        return None
    err = VoxtoolError(f"{len(failed)} of {len(report['rows'])} sources failed (first: {failed[0]['error']})")
    err.exit_code = failed[0]["exit_code"]
    return err
