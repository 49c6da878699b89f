"""agreement.py on hand-made rollouts: a setting's distance to the reference and to the recorded
frames, the reference against itself, and the inputs it refuses."""

import io
import os
import shutil
import subprocess
import sys
import tempfile

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from PIL import Image

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, HERE)
import agreement  # noqa: E402
from fixtures import synthetic_episode, write_dataset  # noqa: E402


def write_rollout(root, videos, column=agreement.GENERATED):
    """A bwm rollout output's frames: one parquet per episode, PNG cells in `column`."""
    for i, video in enumerate(videos):
        cells = []
        for f in video:
            b = io.BytesIO()
            Image.fromarray(f).save(b, format="PNG")
            cells.append({"bytes": b.getvalue(), "path": None})
        path = os.path.join(root, "data", "chunk-000", f"episode_{i:06d}.parquet")
        os.makedirs(os.path.dirname(path), exist_ok=True)
        pq.write_table(pa.table({column: pa.array(cells, pa.struct([("bytes", pa.binary()), ("path", pa.string())]))}), path)


def noisy(video, std, seed):
    rng = np.random.default_rng(seed)
    return np.clip(video.astype(np.float64) + rng.normal(0, std, video.shape), 0, 255).astype(np.uint8)


def test_a_setting_is_scored_against_the_reference_and_the_recorded_frames():
    d = tempfile.mkdtemp()
    try:
        eps = [synthetic_episode("drawer-open-v3", s, length=12, size=32) for s in (1, 2)]
        write_dataset(os.path.join(d, "real"), eps)
        real = [e[1] for e in eps]
        write_rollout(os.path.join(d, "ref"), [noisy(v, 4, 0) for v in real])
        write_rollout(os.path.join(d, "cheap"), [noisy(v, 16, 1) for v in real])
        r = agreement.agreement(os.path.join(d, "ref"), [os.path.join(d, "cheap")], os.path.join(d, "real"), 4)["settings"]
        ref, cheap = r[os.path.join(d, "ref")], r[os.path.join(d, "cheap")]
        assert ref["reference_h"] == 100.0 and ref["episodes"] == 2, ref
        assert 20 < cheap["reference_h"] < ref["recorded_h"], (cheap, ref)
        assert cheap["recorded_h"] < ref["recorded_h"], (cheap, ref)
        # The figures of frames 1..4 are those of the first four generated frames alone.
        g = agreement.frames(os.path.join(d, "cheap", "data", "chunk-000", "episode_000000.parquet"), agreement.GENERATED)
        t = agreement.frames(os.path.join(d, "ref", "data", "chunk-000", "episode_000000.parquet"), agreement.GENERATED)
        assert abs(agreement.score(g, t, 4)[0] - agreement.psnr(g[1:5], t[1:5]).mean()) < 1e-9

        # From the command line, with its JSON; then what it refuses.
        script = os.path.join(HERE, "..", "agreement.py")
        out = os.path.join(d, "a.json")
        p = subprocess.run([sys.executable, script, "--reference", os.path.join(d, "ref"), "--recorded", os.path.join(d, "real"),
                            "--horizon", "4", "--json", out, os.path.join(d, "cheap")], capture_output=True, text=True)
        assert p.returncode == 0 and "against the reference h=4" in p.stdout and os.path.exists(out), p.stdout + p.stderr
        write_rollout(os.path.join(d, "short"), [noisy(real[0], 4, 0)])
        p = subprocess.run([sys.executable, script, "--reference", os.path.join(d, "ref"), os.path.join(d, "short")], capture_output=True, text=True)
        assert p.returncode != 0 and "other episodes than the reference" in p.stderr, p.stderr
        write_dataset(os.path.join(d, "real-short"), eps[:1])
        p = subprocess.run([sys.executable, script, "--reference", os.path.join(d, "ref"), "--recorded", os.path.join(d, "real-short"),
                            os.path.join(d, "cheap")], capture_output=True, text=True)
        assert p.returncode != 0 and "real-short has no episode_000001.parquet" in p.stderr, p.stderr
        write_rollout(os.path.join(d, "video"), [noisy(v, 4, 0) for v in real], column="observation.images.other")
        p = subprocess.run([sys.executable, script, "--reference", os.path.join(d, "ref"), os.path.join(d, "video")], capture_output=True, text=True)
        assert p.returncode != 0 and "--frame-storage image" in p.stderr, p.stderr
    finally:
        shutil.rmtree(d)


if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            fn()
            print(f"{name}: ok")
