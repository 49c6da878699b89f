"""judge.py: a regression of the object's distance to its goal (`obj_to_target`) whose success is
the simulator's rule applied to it. Trained briefly on synthetic frames whose state is drawn (a bar
as long as the drawer is open), partial outcomes included: the state it reads on held-out frames,
the rule following the threshold, `score`, the served response; the training frames with a VAE's
round trips beside the real ones (`train --reconstructed`, sharing the real frames' states); and
what it refuses: a judge.pt of the former classifier, a dataset without the `obj_to_target` column."""

import json
import os
import shutil
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from http.server import ThreadingHTTPServer

import numpy as np
from safetensors.numpy import save_file

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, HERE)
import judge  # noqa: E402
from fixtures import write_dataset  # noqa: E402
from msgpack_numpy import packb  # noqa: E402
from mw import SUCCESS_DISTANCE  # noqa: E402

TASK = "drawer-open-v3"
THRESHOLD_CM = 100 * SUCCESS_DISTANCE[TASK]  # 3 cm
CLOSED_CM = 19.0  # obj_to_target of a closed drawer
FRAMES, SIZE = 10, 32


def drawn(distance_cm, rng):
    """A frame of a drawer `distance_cm` from fully open: a bright bar from the left, longer the
    more it is open (about 1.4 px a cm), on a noisy dark background."""
    frame = rng.integers(0, 40, (SIZE, SIZE, 3), dtype=np.uint8)
    length = 2 + int(round((CLOSED_CM - distance_cm) * 1.4))
    frame[12:20, :length] = (60, 220, 60)
    return frame


def episode(seed, end_cm, length=FRAMES):
    """A pull from closed to `end_cm` from fully open (short of the threshold or past it) over the
    first two thirds of the episode, held there. Successes by the simulator's rule."""
    rng = np.random.default_rng(seed)
    ramp = max(length * 2 // 3, 1)
    distance = np.concatenate([np.linspace(CLOSED_CM, end_cm, ramp), np.full(length - ramp, end_cm)])
    frames = np.stack([drawn(d, rng) for d in distance])
    obj_to_target = (distance / 100).astype(np.float32)
    success = obj_to_target <= np.float32(SUCCESS_DISTANCE[TASK])
    return (TASK, frames, np.zeros((length, 4), np.float32), success, seed, obj_to_target)


def as_reconstructed(frames):
    """What a file of `bwm reconstruct` holds for an episode: u8 [3, F, H, W]."""
    return np.ascontiguousarray((255 - frames).transpose(3, 0, 1, 2))


def expect_exit(argv, *messages):
    try:
        judge.main(argv)
    except SystemExit as e:
        for m in messages:
            assert m in str(e), (m, str(e))
        return str(e)
    raise AssertionError(f"{argv}: no error")


def test_the_window_rule_and_the_bins():
    # One likely frame among unlikely ones does not decide; three in a row do, the least of them.
    z = np.array([-3.0, 2.0, -3.0, -1.0, 1.0, 0.5, 0.8, -2.0])
    f = judge.deciding_frame(z, 3)
    assert f == 5, f
    assert judge.aggregate(judge.phi(z), 3) == judge.phi(z)[5]
    assert judge.deciding_frame(z[:2], 3) == 0  # fewer frames than the window: their least
    # Far from the threshold (p underflows to 0) the frames still rank by their margin.
    far = judge.margin(np.array([19.0, 12.0, 12.0, 12.0, 19.0]), np.full(5, 0.1), THRESHOLD_CM)
    assert judge.phi(far).max() == 0.0 and judge.deciding_frame(far, 3) in (1, 2, 3)
    # The state reported: the closest held for the window (a single near frame does not count).
    assert judge.closest_held(np.array([19.0, 5.0, 19.0, 8.0, 7.0, 7.5, 12.0]), 3) == (3, 8.0)
    assert judge.closest_held(np.array([6.0, 4.0]), 3) == (0, 6.0)
    # Frames that end the episode (final): a success reached in its last w - 1 frames counts, with
    # the frames left; without final it waits for the frames to come; a flicker before does not.
    late = np.array([-3.0, -3.0, -3.0, -3.0, 1.0, 2.0])
    assert late[judge.deciding_frame(late, 3)] < 0 and judge.deciding_frame(late, 3, final=True) == 5
    assert late[judge.deciding_frame(np.array([-3.0, 2.0, -3.0, -3.0]), 3, final=True)] < 0
    assert judge.closest_held(np.array([19.0, 19.0, 19.0, 8.0, 2.5]), 3) == (0, 19.0)
    assert judge.closest_held(np.array([19.0, 19.0, 19.0, 8.0, 2.5]), 3, final=True) == (4, 2.5)
    # Bins closed on the right at the threshold: a state at it is binned with the successes.
    edges = judge.bin_edges(THRESHOLD_CM)
    assert THRESHOLD_CM in edges and np.all(np.diff(edges) > 0) and edges[-1] < judge.CLIP_CM
    b = judge.state_bins(np.array([THRESHOLD_CM, THRESHOLD_CM + 0.01, THRESHOLD_CM - 0.01]), THRESHOLD_CM)
    assert b[0] == b[2] and b[1] == b[0] + 1, b
    near = (np.abs(edges[:-1] - THRESHOLD_CM) <= 1) & (np.abs(edges[1:] - THRESHOLD_CM) <= 1)
    assert near.sum() == 4 and np.diff(edges)[near].max() <= 0.5 < np.diff(edges).max(), edges


def test_the_state_is_learned_and_the_rule_follows_the_threshold():
    folder = tempfile.mkdtemp(prefix="bwm-judge-")
    try:
        train, val = os.path.join(folder, "train"), os.path.join(folder, "val")
        # Pulls that stop anywhere from fully open to well short of the threshold.
        ends = np.linspace(0.0, 14.0, 16)
        write_dataset(train, [episode(i, e, 16) for i, e in enumerate(ends)])
        write_dataset(val, [episode(100 + i, e, 16) for i, e in enumerate([0.5, 2.0, 4.0, 6.0, 9.0, 13.0])])
        out = os.path.join(folder, "judge.pt")
        start = time.time()
        judge.main(["train", "--data", train, "--val", val, "--steps", "80", "--batch", "32", "--lr", "3e-3",
                    "--device", "cpu", "--out", out])
        trained = time.time() - start
        report = json.load(open(os.path.join(folder, "judge.json")))
        assert report["format"] == judge.FORMAT, report
        entry = report["tasks"][TASK]
        assert entry["success_distance_cm"] == THRESHOLD_CM and entry["train_frames"] == 16 * 16, entry
        state = entry["held_out_state"]
        # Predicting the held-out mean would be off by about 5 cm.
        assert state["n"] == 6 * 16 and state["mae_cm"] < 2.5, state
        assert state["near_threshold"]["n"] > 0 and state["near_threshold"]["mae_cm"] is not None, state
        frames = entry["held_out_frames"]
        assert frames["n"] == 6 * 16 and frames["tp"] + frames["fn"] > 0 and frames["balanced_accuracy"] > 0.7, frames
        assert entry["held_out_episodes"]["n"] == 6 and entry["held_out_episodes"]["closest_mae_cm"] is not None, entry

        # The rule on the regressed state: frames far below the threshold are judged successes far
        # more often than frames far above it, and p falls as the state grows.
        model = judge.Judge(out, "cpu", None)
        h = judge.load_all([val], 1 << 30, 0, [TASK])[TASK]
        mu, scale = judge.predict(model.models[TASK], h["frames"], "cpu")
        p = judge.phi(judge.margin(mu, scale, THRESHOLD_CM))
        truth = judge.target_cm(h["obj_to_target"])
        below, above = p[truth <= THRESHOLD_CM - 2] > 0.5, p[truth >= THRESHOLD_CM + 3] > 0.5
        assert len(below) and len(above) and below.mean() > above.mean() + 0.6, (below.mean(), above.mean())
        assert np.corrcoef(truth, mu)[0, 1] > 0.8, np.corrcoef(truth, mu)

        # score: the same measures on the held-out frames and on a "round trip" (here the frames
        # themselves), with the real frames' report matching training's.
        rec = os.path.join(folder, "val.safetensors")
        eps = judge.read_jsonl(os.path.join(val, "meta", "episodes.jsonl"))
        save_file({f"episode.{e['episode_index']}": np.ascontiguousarray(
            episode(100 + e["episode_index"], [0.5, 2.0, 4.0, 6.0, 9.0, 13.0][e["episode_index"]], 16)[1].transpose(3, 0, 1, 2))
            for e in eps}, rec)
        scored = os.path.join(folder, "score.json")
        judge.main(["score", "--model", out, "--val", val, "--reconstructed", rec, "--device", "cpu", "--out", scored])
        s = json.load(open(scored))["tasks"][TASK]
        for part in ("real", "reconstructed"):
            assert s[part]["frames"]["n"] == 6 * 16 and s[part]["episodes"]["n"] == 6, s
            assert abs(s[part]["state"]["mae_cm"] - state["mae_cm"]) < 1e-3, (s[part]["state"], state)
        assert s["real"]["frames"]["accuracy"] == frames["accuracy"], (s, frames)
        judge.main(["score", "--model", out, "--val", val, "--device", "cpu", "--out", scored])
        alone = json.load(open(scored))["tasks"][TASK]
        assert alone["real"] == s["real"] and "reconstructed" not in alone and "reconstruction_psnr_db" not in alone, alone

        # Served: success_probability (what bwm evaluate reads) and the estimated state.
        server = ThreadingHTTPServer(("127.0.0.1", 0), judge.handler(model, 1 << 24))
        threading.Thread(target=server.serve_forever, daemon=True).start()
        try:
            url = f"http://127.0.0.1:{server.server_address[1]}/judge"
            replies = {}
            for name, end in (("open", 0.5), ("short", 12.0)):
                body = packb({"frames": episode(7, end, 16)[1], "task": TASK, "prompt": "open the drawer"})
                with urllib.request.urlopen(urllib.request.Request(url, data=body, method="POST")) as r:
                    replies[name] = json.loads(r.read())
            for reply in replies.values():
                assert {"success_probability", "obj_to_target_cm"} <= set(reply), reply
                assert 0 <= reply["success_probability"] <= 1 and 0 <= reply["frame"] < 16 and reply["model"] == TASK, reply
                assert reply["success_distance_cm"] == THRESHOLD_CM and len(json.dumps(reply)) < 300, reply
            assert replies["open"]["success_probability"] >= 0.5 > replies["short"]["success_probability"], replies
            assert replies["open"]["obj_to_target_cm"] < THRESHOLD_CM < replies["short"]["obj_to_target_cm"], replies
            # "final" must be a boolean: anything else is refused, naming it.
            body = packb({"frames": episode(7, 0.5, 16)[1], "task": TASK, "final": "yes"})
            try:
                urllib.request.urlopen(urllib.request.Request(url, data=body, method="POST"))
                raise AssertionError("a non-boolean final was accepted")
            except urllib.error.HTTPError as e:
                assert e.code == 400 and "'final'" in json.loads(e.read())["error"], e
        finally:
            server.shutdown()
        print(f"  trained in {trained:.0f} s; held-out state MAE {state['mae_cm']:.2f} cm, success rule balanced accuracy "
              f"{frames['balanced_accuracy']:.3f}; p > 0.5 on {below.mean():.2f} of frames 2 cm inside, {above.mean():.2f} 3 cm outside")
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def test_reconstructed_frames_are_added_with_the_real_states():
    folder = tempfile.mkdtemp(prefix="bwm-judge-")
    try:
        data = os.path.join(folder, "train")
        episodes = [episode(0, 1.0), episode(1, 2.5), episode(2, 8.0)]
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
        for k in ("success", "obj_to_target", "episode", "row"):
            assert np.array_equal(both[k][: 3 * FRAMES], real[k]), k
        assert sorted(set(both["episode"][added].tolist())) == [0, 2]
        for at in np.flatnonzero(added):
            e, row = both["episode"][at], both["row"][at]
            source = episodes[e][1][row]
            assert np.array_equal(both["frames"][at], 255 - source), (e, row)
            assert both["obj_to_target"][at] == episodes[e][5][row], (e, row)
            assert both["success"][at] == episodes[e][3][row], (e, row)

        # Training with them: the report counts them; held-out scores stay on real frames.
        out = os.path.join(folder, "judge.pt")
        judge.main(["train", "--data", data, "--reconstructed", rec, "--val", data, "--steps", "2", "--batch", "8",
                    "--device", "cpu", "--out", out])
        report = json.load(open(os.path.join(folder, "judge.json")))
        assert report["reconstructed"] == [rec], report
        entry = report["tasks"][TASK]
        assert entry["train_frames"] == 5 * FRAMES and entry["train_reconstructed_frames"] == 2 * FRAMES, entry
        assert entry["held_out_frames"]["n"] == 3 * FRAMES and entry["held_out_state"]["n"] == 3 * FRAMES, entry

        # A file per dataset, and one that holds episodes of this dataset.
        other = os.path.join(folder, "other.safetensors")
        save_file({"episode.7": as_reconstructed(episodes[0][1])}, other)
        for bad, message in (([rec, rec], "one per dataset"), ([other], "holds none")):
            expect_exit(["train", "--data", data, "--reconstructed", *bad, "--steps", "1", "--device", "cpu", "--out", out], message)
        # A file whose frames do not fit the dataset's.
        save_file({"episode.0": as_reconstructed(episodes[0][1])[:, :, :16]}, rec)
        expect_exit(["train", "--data", data, "--reconstructed", rec, "--steps", "1", "--device", "cpu", "--out", out], "not [3, F, H, W]")
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def test_former_judges_and_datasets_without_the_state_are_refused():
    import torch

    folder = tempfile.mkdtemp(prefix="bwm-judge-")
    try:
        # A classifier's judge.pt (format 1): every subcommand that reads it says to train again.
        old = os.path.join(folder, "judge.pt")
        torch.save({"format": "bwm-metaworld-judge/1", "window": 3, "models": {}}, old)
        try:
            judge.Judge(old, "cpu", None)
        except ValueError as e:
            assert "bwm-metaworld-judge/1" in str(e) and "train it again" in str(e), e
        else:
            raise AssertionError("a judge.pt of format 1: no error")
        expect_exit(["serve", "--model", old, "--port", "0", "--device", "cpu"], "former format", "train it again")
        other = os.path.join(folder, "other.pt")
        torch.save({"weights": torch.zeros(1)}, other)
        expect_exit(["serve", "--model", other, "--port", "0", "--device", "cpu"], "is not a judge model")

        # A dataset written before generate.py wrote the state, to learn from or to be scored on:
        # the column named, and what to do.
        before, now = os.path.join(folder, "before"), os.path.join(folder, "now")
        write_dataset(before, [e[:5] for e in (episode(0, 1.0), episode(1, 8.0))])
        write_dataset(now, [episode(0, 1.0), episode(1, 8.0)])
        new = os.path.join(folder, "new.pt")
        for argv in (["train", "--data", before], ["train", "--data", now, "--val", before]):
            said = expect_exit(argv + ["--steps", "1", "--device", "cpu", "--out", new], "`obj_to_target` column",
                               "regenerate it with the current generate.py")
            assert before in said and not os.path.exists(new), said
    finally:
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            start = time.time()
            fn()
            print(f"{name}: ok ({time.time() - start:.0f} s)", flush=True)
