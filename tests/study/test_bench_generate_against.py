"""`hydrabench bench generate --against`: this checkout and another one generate in turn, with the same
bytes. (A file of its own, apart from tests/study/test_bench_generate.py, so that `make test`'s
`--dist loadfile` can run the two long end-to-end runs on different workers.)"""

import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from study.cli import main

ROOT = Path(__file__).resolve().parents[2]


def test_bench_generate_against_a_copy_of_this_code_runs_both_in_turn_with_the_same_bytes(tmp_path):
    # another checkout of the same code: its packages link to this one's (so the compiled kernels'
    # cache is shared and the test does not compile them all again)
    copy = tmp_path / "copy"
    copy.mkdir()
    for part in ("sim", "sensors", "fusion", "study", "configs"):
        (copy / part).symlink_to(ROOT / part, target_is_directory=True)
    cmd = [sys.executable, "-m", "study.cli", "bench", "generate", "--against", str(copy), "--profiles", "cpu",
           "--workers", "1", "--contexts", "city,fog", "--frames-per-context", "1", "--sequence-length", "1",
           "--rounds", "2", "--json"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=ROOT,
                         env={**os.environ, "HYDRABENCH_PROGRESS_S": "0"})
    assert run.returncode == 0, run.stderr[-2000:]
    r = json.loads(run.stdout)
    here, there = str(ROOT.resolve()), str(copy.resolve())
    assert r["this"]["dir"] == here and r["against"] == [{"dir": there, "commit": None}]
    assert [(x["round"], x["dir"]) for x in r["runs"]] == [(0, here), (0, there), (1, here), (1, there)]
    assert all(x["frames"] == 2 and x["frames_per_second"] > 0 and x["same_bytes"] for x in r["runs"])
    assert r["contexts"] == ["city", "fog"]  # each side was asked for these two (the child's --contexts)
    med = {d: statistics.median(x["frames_per_second"] for x in r["runs"] if x["dir"] == d) for d in (here, there)}
    assert r["ratios"] == {"cpu/1": {there: round(med[here] / med[there], 3)}}
    assert r["same_bytes"] == {there: True}
    assert run.stderr.count("bench generate: round") == 4  # a progress line per run, also into a log


def test_bench_generate_against_refuses_what_is_not_another_checkout(tmp_path, capsys):
    for argv, needle in [
        (["--against", str(tmp_path)], "not a hydrabench checkout"),
        (["--against", str(ROOT)], "names this checkout"),
        (["--against", f"{tmp_path},{tmp_path}"], "names a directory twice"),
        (["--against", str(ROOT), "--start-methods", "fork"], "leave out --start-methods"),
    ]:
        assert main(["bench", "generate", *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], (argv, err)
