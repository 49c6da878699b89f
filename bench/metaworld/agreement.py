"""How close generated episodes come to a reference rollout of the same episodes, and to the recorded
frames: the real-time issue's question of a cheaper setting (fewer sampler steps, a distilled
student, a light decoder) against the full one (50 Euler steps, the VAE's decoder).

    python agreement.py --reference DIR [--recorded DATASET] [--horizon 32] [--json OUT] DIR ...

Each DIR is a `bwm rollout --frame-storage image` output (its frames as PNG cells of the column
`observation.images.generated`), all of the same episodes and actions; DATASET the dataset they
were rolled out from (its frames as PNG cells, generate.py's `observation.image`). Per setting the
mean over episodes of the mean PSNR (dB) over frames 1..h (the generated ones; frame 0 is the real
x0) and over whole episodes, against the reference's frames and against the recorded ones. The
sampler's noise is keyed by the rollout's seed, so settings rolled out with the same seed differ
only by what they change."""

import argparse
import glob
import io
import os
import sys

import numpy as np
import pyarrow.parquet as pq
from PIL import Image

from files import write_json

GENERATED = "observation.images.generated"
RECORDED = "observation.image"


def frames(path: str, column: str) -> np.ndarray:
    """The frames [T, H, W, 3] (float64, 0-255) of one episode's parquet file."""
    names = pq.read_schema(path).names
    if column not in names:
        raise SystemExit(f"agreement: {path} has no column {column} (its frames as PNG cells: `bwm rollout --frame-storage image`); it has {', '.join(names)}")
    cells = pq.read_table(path, columns=[column]).column(column).to_pylist()
    return np.stack([np.asarray(Image.open(io.BytesIO(c["bytes"])).convert("RGB"), np.float64) for c in cells])


def psnr(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per frame, of 0-255 frames; identical frames count as 100 dB."""
    mse = ((a - b) ** 2).mean(axis=(1, 2, 3))
    return np.where(mse > 0, 10 * np.log10(255.0 ** 2 / np.maximum(mse, 1e-12)), 100.0)


def episodes(root: str) -> dict:
    found = {os.path.basename(p): p for p in sorted(glob.glob(os.path.join(root, "data", "chunk-*", "episode_*.parquet")))}
    if not found:
        raise SystemExit(f"agreement: {root} holds no episode (data/chunk-*/episode_*.parquet)")
    return found


def score(generated: np.ndarray, other: np.ndarray, horizon: int) -> tuple[float, float]:
    n = min(len(generated), len(other))
    per_frame = psnr(generated[1:n], other[1:n])
    return float(per_frame[:horizon].mean()), float(per_frame.mean())


def agreement(reference: str, settings: list[str], recorded: str | None, horizon: int) -> dict:
    refs = episodes(reference)
    truth = episodes(recorded) if recorded else {}
    roots = list(dict.fromkeys([reference, *settings]))  # the reference may be named among them
    found = {}
    for root in roots:
        found[root] = episodes(root)
        if set(found[root]) != set(refs):
            raise SystemExit(f"agreement: {root} holds other episodes than the reference {reference}")
    missing = sorted(set(refs) - set(truth)) if truth else []
    if missing:
        raise SystemExit(f"agreement: {recorded} has no {missing[0]}")
    rows = {root: {"reference_h": [], "reference_full": [], "recorded_h": [], "recorded_full": []} for root in roots}
    # Episode by episode, so that the reference's and the recorded frames are decoded once each and
    # only one episode's frames are held at a time.
    for name in refs:
        ref = frames(refs[name], GENERATED)
        real = frames(truth[name], RECORDED) if truth else None
        for root in roots:
            g = ref if root == reference else frames(found[root][name], GENERATED)
            h, full = score(g, ref, horizon)
            rows[root]["reference_h"].append(h)
            rows[root]["reference_full"].append(full)
            if real is not None:
                h, full = score(g, real, horizon)
                rows[root]["recorded_h"].append(h)
                rows[root]["recorded_full"].append(full)
    out = {root: {"episodes": len(refs), **{k: float(np.mean(v)) for k, v in rows[root].items() if v}} for root in roots}
    return {"reference": reference, "horizon": horizon, "settings": out}




def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reference", required=True, help="the reference setting's bwm rollout output")
    ap.add_argument("--recorded", help="the dataset the episodes were rolled out from (its recorded frames)")
    ap.add_argument("--horizon", type=int, default=32, help="generated frames the first figure averages over (default 32)")
    ap.add_argument("--json", help="write the figures here too")
    ap.add_argument("settings", nargs="*", help="other settings' bwm rollout outputs")
    a = ap.parse_args(argv)
    if a.horizon < 1:
        ap.error("--horizon must be at least 1")
    result = agreement(a.reference, a.settings, a.recorded, a.horizon)
    h = a.horizon
    for root, r in result["settings"].items():
        line = f"{root}: against the reference h={h} {r['reference_h']:.2f} dB, whole episodes {r['reference_full']:.2f} dB"
        if "recorded_h" in r:
            line += f"; against the recorded frames h={h} {r['recorded_h']:.2f} dB, whole episodes {r['recorded_full']:.2f} dB"
        print(line + f" ({r['episodes']} episodes)")
    if a.json:
        write_json(a.json, result)


if __name__ == "__main__":
    sys.exit(main())
