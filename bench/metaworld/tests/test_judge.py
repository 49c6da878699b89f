"""judge.py's training frames with a VAE's round trips beside the real ones (`train --reconstructed`):
which frames are added, with which flags, and the errors of a file that does not fit the data."""

import json
import os
import shutil
import sys
import tempfile

import numpy as np
from safetensors.numpy import save_file

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, HERE)
import judge  # noqa: E402
from fixtures import write_dataset  # noqa: E402

TASK = "drawer-open-v3"
FRAMES, SIZE = 10, 32


def episode(seed, shade):
    """Dark frames that turn bright from the middle on, flagged as successes there."""
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 40, (FRAMES, SIZE, SIZE, 3), dtype=np.uint8)
    frames[FRAMES // 2:] += np.uint8(shade)
    success = np.arange(FRAMES) >= FRAMES // 2
    return (TASK, frames, np.zeros((FRAMES, 4), np.float32), success, seed)


def as_reconstructed(frames):
    """What a file of `bwm reconstruct` holds for an episode: u8 [3, F, H, W]."""
    return np.ascontiguousarray((255 - frames).transpose(3, 0, 1, 2))


def test_reconstructed_frames_are_added_with_the_real_flags():
    folder = tempfile.mkdtemp(prefix="bwm-judge-")
    try:
        data = os.path.join(folder, "train")
        episodes = [episode(0, 150), episode(1, 180), episode(2, 200)]
        write_dataset(data, episodes)
        # Episodes 0 and 2 reconstructed (as `--max-episodes` or another order would leave it).
        rec = os.path.join(folder, "rec.safetensors")
        save_file({"episode.0": as_reconstructed(episodes[0][1]), "episode.2": as_reconstructed(episodes[2][1])}, rec)

        real = judge.load_all([data], 1 << 30, 0, [TASK])[TASK]
        both = judge.load_all([data], 1 << 30, 0, [TASK], [rec])[TASK]
        assert len(real["success"]) == 3 * FRAMES and "reconstructed" not in real
        assert len(both["success"]) == 5 * FRAMES, len(both["success"])
        added = both["reconstructed"]
        assert added.sum() == 2 * FRAMES and not added[: 3 * FRAMES].any()
        for k in ("success", "episode", "row"):
            assert np.array_equal(both[k][: 3 * FRAMES], real[k]), k
        assert sorted(set(both["episode"][added].tolist())) == [0, 2]
        for at in np.flatnonzero(added):
            e, row = both["episode"][at], both["row"][at]
            source = episodes[e][1][row]
            assert np.array_equal(both["frames"][at], 255 - source), (e, row)
            assert both["success"][at] == episodes[e][3][row], (e, row)

        # Training with them: the report counts them; held-out scores stay on real frames.
        out = os.path.join(folder, "judge.pt")
        judge.main(["train", "--data", data, "--reconstructed", rec, "--val", data, "--steps", "2", "--batch", "8",
                    "--device", "cpu", "--out", out])
        report = json.load(open(os.path.join(folder, "judge.json")))
        assert report["reconstructed"] == [rec], report
        entry = report["tasks"][TASK]
        assert entry["train_frames"] == 5 * FRAMES and entry["train_reconstructed_frames"] == 2 * FRAMES, entry
        assert entry["held_out_frames"]["n"] == 3 * FRAMES, entry

        # A file per dataset, and one that holds episodes of this dataset.
        other = os.path.join(folder, "other.safetensors")
        save_file({"episode.7": as_reconstructed(episodes[0][1])}, other)
        for bad, message in (([rec, rec], "one per dataset"), ([other], "holds none")):
            try:
                judge.main(["train", "--data", data, "--reconstructed", *bad, "--steps", "1", "--device", "cpu", "--out", out])
            except SystemExit as e:
                assert message in str(e), e
            else:
                raise AssertionError(f"{bad}: no error")
        # A file whose frames do not fit the dataset's.
        save_file({"episode.0": as_reconstructed(episodes[0][1])[:, :, :16]}, rec)
        try:
            judge.main(["train", "--data", data, "--reconstructed", rec, "--steps", "1", "--device", "cpu", "--out", out])
        except SystemExit as e:
            assert "not [3, F, H, W]" in str(e), e
        else:
            raise AssertionError("a reconstruction of another size: no error")
    finally:
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            fn()
            print(f"{name}: ok")
