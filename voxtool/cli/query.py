"""`voxtool query`: the state of a map at points."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import emit, handle_errors


def read_points(path: Path):
    """N x 3 coordinates from a .csv (x,y,z per line; a header line is skipped) or a .pcd."""
    import warnings

    import numpy as np

    from voxtool.errors import SourceError

    if path.suffix.lower() == ".pcd":
        from voxtool.sources.pcd import read_pcd

        return read_pcd(path).xyz.astype(np.float64)
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            at, first = next(((i, ln) for i, ln in enumerate(f, 1) if ln.strip()), (0, ""))
    except OSError as err:
        raise SourceError(f"{path}: cannot read: {err.strerror}") from err
    header = bool(first) and first.lstrip()[0] not in "+-.0123456789"
    try:  # numpy's C parser: a million lines in about half a second
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": zero points is an answer
            pts = np.loadtxt(path, delimiter="," if "," in first else None, skiprows=at if header else 0, usecols=(0, 1, 2),
                             ndmin=2, dtype=np.float64)
    except ValueError:
        raise SourceError(f"{path}: {_first_bad_line(path, header)}") from None
    return pts.reshape(-1, 3)


def _first_bad_line(path: Path, header: bool) -> str:
    """Where a points file stops being x,y,z numbers (numpy's own message counts rows its own way)."""
    with open(path, encoding="utf-8", errors="replace") as f:
        for number, line in enumerate(f, 1):
            if not line.strip():
                continue
            if header:  # the first non-blank line
                header = False
                continue
            values = line.replace(",", " ").split()[:3]
            try:
                if len(values) == 3:
                    [float(v) for v in values]
                    continue
            except ValueError:
                pass
            return f"line {number} is not x, y, z numbers: {line.strip()[:60]!r}"
    return "not x, y, z numbers"


@click.command(context_settings={"ignore_unknown_options": True})  # so that -20 is a coordinate, not an option
@click.argument("map_file", type=click.Path(path_type=Path))
@click.argument("xyz", nargs=3, type=float, required=False)
@click.option("--points", type=click.Path(path_type=Path), help="Query every point of a .csv (x,y,z) or .pcd file.")
@click.option("-o", "--output", type=click.Path(path_type=Path),
              help="--points: write the answers as CSV (x,y,z,state,probability,depth; state as a word: occupied, "
                   "free, unknown) instead of a summary.")
@click.option("--json", "as_json", is_flag=True, help="Print as JSON (per point for X Y Z; counts for --points).")
@handle_errors
def query(map_file, xyz, points, output, as_json):
    """Is a point occupied? The state (occupied / free / unknown), the occupancy probability and
    the depth of the leaf that answered (16: a single voxel; less: a pruned, larger leaf), at X Y Z
    (metres, map frame) or at every point of --points.

    \b
      voxtool query map.vxm 1.0 2.5 0.3
      voxtool query map.vxm --json -4.2 1.0 -0.3
      voxtool query map.vxm --points pts.csv -o answers.csv"""
    import numpy as np

    from voxtool.errors import ParameterError
    from voxtool.voxelmap import STATE_NAMES, load

    if (points is None) == (not xyz):
        raise ParameterError("give X Y Z or --points FILE")
    pts = np.array([xyz], dtype=np.float64) if xyz else read_points(points)
    vmap = load(map_file)
    answer = vmap.query(pts)
    if xyz:
        state = STATE_NAMES[int(answer["state"][0])]
        prob = float(answer["probability"][0])
        result = {"x": xyz[0], "y": xyz[1], "z": xyz[2], "state": state,
                  "probability": None if np.isnan(prob) else round(prob, 6), "depth": int(answer["depth"][0])}
        emit(result, as_json, [("state", state), ("probability", "-" if np.isnan(prob) else f"{prob:.4f}"),
                               ("leaf depth", str(result["depth"]))])
        return
    counts = np.bincount(answer["state"], minlength=3)
    result = {"points": int(pts.shape[0]), **{name: int(c) for name, c in zip(STATE_NAMES, counts)}}
    if output is not None:
        from itertools import chain

        from voxtool.atomic import atomic_writer

        names = np.array(STATE_NAMES, dtype=object)[answer["state"]]  # words, as the text and JSON say
        columns = (pts[:, 0], pts[:, 1], pts[:, 2], names, answer["probability"], answer["depth"])
        with atomic_writer(output) as f:
            f.write(b"x,y,z,state,probability,depth\n")
            # one %-format per block of rows, not one per row (np.savetxt): 1M rows 2.7 s -> 1.2 s
            row = "%.6f,%.6f,%.6f,%s,%.6f,%d\n"
            for start in range(0, len(pts), 65_536):
                block = [c[start:start + 65_536].tolist() for c in columns]
                f.write(((row * len(block[0])) % tuple(chain.from_iterable(zip(*block)))).encode())
    emit(result, as_json, [(k, f"{v:,}") for k, v in result.items()], written=output)
