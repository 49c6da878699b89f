"""files.py: a result is written whole or not at all, and a cut one reads as missing."""

import os
import sys
import tempfile

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import files  # noqa: E402


def test_a_write_that_fails_leaves_the_earlier_file_and_no_temporary():
    with tempfile.TemporaryDirectory() as root:
        path = os.path.join(root, "study.json")
        files.write_json(path, {"r": 0.9})
        try:
            with files.replacing(path) as f:
                f.write('{"r": 0.')
                raise KeyboardInterrupt  # a run cut short mid-write
        except KeyboardInterrupt:
            pass
        else:
            raise AssertionError("the interruption was swallowed")
        assert files.read_json(path) == {"r": 0.9}
        assert os.listdir(root) == ["study.json"], os.listdir(root)


def test_binary_and_text_writes_land_whole():
    with tempfile.TemporaryDirectory() as root:
        with files.replacing(os.path.join(root, "a.bin"), "wb") as f:
            f.write(b"\x00\x01")
        files.write_text(os.path.join(root, "a.txt"), "x,y\n")
        assert open(os.path.join(root, "a.bin"), "rb").read() == b"\x00\x01"
        assert open(os.path.join(root, "a.txt")).read() == "x,y\n"
        assert sorted(os.listdir(root)) == ["a.bin", "a.txt"]


def test_a_missing_or_truncated_cache_reads_as_none():
    with tempfile.TemporaryDirectory() as root:
        path = os.path.join(root, "truth.json")
        assert files.read_json(path) is None
        open(path, "w").write('{"key": {"episodes": [1, 2')  # what a plain copy cut short leaves
        assert files.read_json(path) is None
        files.write_json(path, {"key": 1})
        assert files.read_json(path) == {"key": 1}
        assert open(path).read().endswith("}\n")


if __name__ == "__main__":
    for name, fn in list(globals().items()):
        if name.startswith("test_"):
            fn()
            print(f"{name}: ok")
