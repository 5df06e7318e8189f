"""`hydrabench study`: the argparse adapter of `study.pipeline.stages.run_study` (stages, caching and the
report are described there and in `study.report.build`)."""

from __future__ import annotations

from pathlib import Path

from study.cli import Formatter, count_int, emit, out_dir, study_config, workers_int

EPILOG = """\
stages: generate -> train -> gatedata -> gates -> evaluate -> report. Each stage's output is kept in
DIR/stages/<stage>-<key>/, keyed by its config section and the digests of what it reads; a done stage
is skipped, an interrupted one (even kill -9) continues where it stopped, and a changed field reruns
only its stage and the stages below it. DIR/report.md, DIR/report.html (self-contained) and
DIR/report.json hold the results.

examples:
  hydrabench study smoke --out out/smoke                 (minutes; numbers mean nothing)
  hydrabench study cpu --out out/cpu --json > cpu.json   (the first 2-core study: ~75 min on 2 cores)
  hydrabench study cpu-frontier --out out/cpu-frontier   (the same with the budget frontier's recipe)
  hydrabench study cpu-verdict --out out/cpu-verdict     (its detectors adopted, a gate set and a test set sized
                                                          to replicate: ~1.5 h)
  hydrabench study cpu-long --out out/cpu-long           (the same at the reference runs' size: days)
  hydrabench study paper --out out/paper --device cuda   (for a GPU)
  hydrabench study my_study.yaml --out out/mine --until train
presets: configs/study/*.yaml (tiny, smoke, cpu, cpu-frontier, cpu-verdict, cpu-long, paper); a YAML file takes the same keys (unknown keys
are errors).
"""


def add_parser(sub, name, help_text):
    import study.pipeline.stages as stages

    p = sub.add_parser(name, help=help_text, description=stages.__doc__, epilog=EPILOG, formatter_class=Formatter)
    p.add_argument("config", metavar="CONFIG", type=study_config,
                   help="a preset (tiny, smoke, cpu, cpu-frontier, cpu-verdict, cpu-long, paper) or a YAML file of StudyConfig fields")
    p.add_argument("--out", required=True, type=out_dir,
                   help="study directory (created; an existing study is continued; a folder of other files is refused)")
    p.add_argument("--until", default="report", choices=list(stages.STAGES), help="stop after this stage")
    p.add_argument("--device", default=None, choices=["auto", "cpu", "cuda"],
                   help="where networks run (overrides the config's run.device) [the config's]")
    p.add_argument("--threads", type=count_int, default=None,
                   help="torch CPU threads, 0 = the cores available (overrides run.threads) [the config's]")
    p.add_argument("--workers", type=workers_int, default=None,
                   help="generation processes (overrides run.workers) [the config's]")
    p.add_argument("--backend", default=None, choices=["local", "ray"],
                   help="generation backend: local processes or one Ray task per shard (overrides run.backend) "
                   "[the config's]")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object on stdout: the stages and every number of the report")
    p.set_defaults(run=run)


def run(args) -> int:
    import dataclasses

    from study.engine.device import resolve_device
    from study.pipeline.stages import run_study

    cfg = args.config
    over = {k: v for k, v in (("device", args.device), ("threads", args.threads), ("workers", args.workers),
                              ("backend", args.backend)) if v is not None}
    if over:
        cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, **over))
    resolve_device(device=cfg.run.device, threads=cfg.run.threads, apply=False)  # a missing GPU: refused first
    result = run_study(cfg, Path(args.out), until=args.until)

    def text(r):
        lines = [f"study {r['out']}: {r['seconds']} s"]
        for n, s in r["stages"].items():
            lines.append(f"  {n:9s} {s['status']:8s} {s['seconds']:8.1f} s  {s['dir']}")
        if "report" in r:
            lines.append(f"  report: {r['report']['report.md']}, {r['report']['report.html']}")
        return "\n".join(lines)

    emit(result, args.json, text)
    return 0
