"""Every command keeps the CLI contract under bad input and damaged data (DESIGN.md, README "contract").

The commands and their options are read from the parser (`study.cli.build_parser()`), so a command or
option added later is fuzzed the day it is added. Each option gets the bad values of its kind: the
argument types of `study.cli` carry a `kind` (count with bounds, finite number, name list, output
file with its extensions, output or cache directory, dataset, training run, checkpoint), `choices`
give an unknown choice, untyped options get unknown names. Every dataset-taking command also gets
damaged copies of a small fixture dataset (wrong JSON types, invalid JSON, truncated and flipped
arrays, missing files). For every case:

    exit code 2, nothing on stdout, exactly one line on stderr naming what is wrong (the option, its
    value or the damaged file), no "Traceback", and no file or directory created or changed.

Commands run in-process through `study.cli.main(argv)`; a few run as subprocesses to check the
installed entry point end to end. The number of cases tried is printed (pytest -s) and asserted.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from study.cli import build_parser, main
from tests.conftest import NARROW_ARGS, NARROW_MODEL

# Values for required options that no type describes: a valid example each (the fuzz needs a valid
# command around the one bad value). A new required option without a kind must be added here.
EXAMPLES = {"--gate": "deep", "--name": "mini"}
BOGUS = "__bogus__"
TRACKED: list[tuple[str, float]] = []  # (case, seconds) of every case tried, for the count
CASES_BY_TEST: dict[str, int] = {}  # test name -> cases it tried
CONTRIBUTORS = {"test_every_option_of_every_command_refuses_its_bad_values",
                "test_every_dataset_argument_refuses_damaged_datasets_naming_the_file",
                "test_verify_json_reports_every_damage_on_stdout", "test_unknown_flags_and_missing_arguments_are_named",
                "test_help_explains_every_option_without_noise", "test_entry_point_end_to_end_in_a_subprocess",
                "test_generate_refuses_a_folder_of_other_files_and_duplicates",
                "test_train_on_a_one_sequence_dataset_writes_its_checkpoint_and_reports_no_map",
                "test_every_run_argument_refuses_damaged_checkpoints_naming_the_file",
                "test_generate_refuses_a_damaged_shard_in_its_out_and_leaves_no_partial_shard",
                "test_generate_refuses_an_out_another_generate_is_writing",
                "test_study_config_is_checked_whole_before_its_first_stage",
                "test_train_refuses_an_out_another_train_is_writing",
                "test_ctrl_c_to_generate_with_workers_prints_one_line",
                "test_evaluate_names_the_missing_epoch_and_the_epochs_there",
                "test_every_workers_option_has_the_one_bound", "test_an_unusable_cache_location_is_one_line_before_work",
                "test_an_empty_home_puts_no_cache_at_the_file_system_root",
                "test_a_full_disk_during_generate_is_one_line_and_leaves_nothing_partial",
                "test_compare_refuses_a_plot_without_intervals_before_the_networks_run",
                "test_study_refuses_a_typo_before_importing_torch"}
"""The tests that try cases; the count test checks that each of them ran and tried some."""


@pytest.fixture(autouse=True)
def _count_cases(request):
    """Count the cases each test of this file tried (TRACKED grows while it runs)."""
    before = len(TRACKED)
    yield
    if len(TRACKED) > before:  # (a parametrized test's cases add up under its name)
        name = request.node.originalname
        CASES_BY_TEST[name] = CASES_BY_TEST.get(name, 0) + len(TRACKED) - before


# ---------------------------------------------------------------------------------------------
# fixtures: one small dataset, one tiny trained run, and the damaged copies


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from sensors.generate import GenerateConfig, generate
    from study.engine.train import TrainConfig, train

    root = tmp_path_factory.mktemp("fuzz")
    data = root / "data"
    generate(GenerateConfig(contexts=("junction",), frames_per_context=2, sequence_length=1, seed=3), data,
             workers=1, progress=False)
    run = root / "run"
    train(TrainConfig(data=str(data), branches=("camera_right",), epochs=1, batch_size=1, warmup_steps=1,
                      threads=2, eval_frames=1, model=NARROW_MODEL), run, progress=False)
    box = root / "box"  # the working directory of every case
    box.mkdir()
    (root / "a_file").write_text("not a directory\n")
    (root / "empty_dir").mkdir()
    foreign = root / "foreign"  # a folder of someone else's files
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine\n")
    (root / "bad.yaml").write_text("frames_per_context: [1,\n")
    (root / "wrong_types.yaml").write_text("frames_per_context: many\n")
    (root / "list.yaml").write_text("- 1\n- 2\n")
    (root / "unknown_key.yaml").write_text("frames_per_contxt: 3\n")
    (root / "latin1.yaml").write_bytes("frames_per_context: 3  # caf\u00e9\n".encode("latin-1"))  # not UTF-8
    (root / "links").mkdir()
    os.symlink("loop", root / "links" / "loop")  # a symbolic link loop
    damaged = root / "damaged"
    damaged.mkdir()
    for name, (culprit, damage) in DAMAGES.items():
        copy = damaged / name
        shutil.copytree(data, copy)
        damage(copy)
        if culprit != "manifest.json":
            _rehash(copy)  # checksums that match the damage: verify must find it as the other commands do
    damaged_runs = root / "damaged_runs"  # (outside "damaged": the snapshot sees every file of these)
    damaged_runs.mkdir()
    for name, (_, damage, _) in RUN_DAMAGES.items():
        copy = damaged_runs / name
        shutil.copytree(run, copy)
        damage(copy)
    predictions = root / "predictions"  # a predictions directory as far as parsing reads it (its manifest's format)
    predictions.mkdir()
    (predictions / "manifest.json").write_text('{"format": "hydrabench-predictions"}\n')
    return {"root": root, "data": data, "run": run, "box": box, "damaged": damaged, "damaged_runs": damaged_runs,
            "predictions": predictions}


def _rehash(d: Path) -> None:
    """Record each present shard's checksum in the manifest, as a tool that damaged the data and then
    rewrote the manifest would (only the structural check can tell then)."""
    from sensors.dataset import shard_digest

    m = json.loads((d / "manifest.json").read_text())
    for s in m["shards"]:
        if (d / s["name"]).is_dir():
            s["sha256"] = shard_digest(d / s["name"])
    (d / "manifest.json").write_text(json.dumps(m, indent=1))


def _write(path: Path, text: str) -> None:
    path.write_text(text)


def _edit_manifest(edit):
    def damage(d: Path) -> None:
        m = json.loads((d / "manifest.json").read_text())
        edit(m)
        (d / "manifest.json").write_text(json.dumps(m))
    return damage


def _truncate(rel: str, keep: float = 0.5):
    def damage(d: Path) -> None:
        p = d / rel
        b = p.read_bytes()
        p.write_bytes(b[: int(len(b) * keep)])
    return damage


def _flip(rel: str, at: slice):
    def damage(d: Path) -> None:
        p = d / rel
        b = bytearray(p.read_bytes())
        b[at] = bytes(255 - x for x in b[at])
        p.write_bytes(bytes(b))
    return damage


def _remove(rel: str):
    def damage(d: Path) -> None:
        p = d / rel
        shutil.rmtree(p) if p.is_dir() else p.unlink()
    return damage


def _reversed_offsets(d: Path) -> None:
    p = d / "shard-00000" / "lidar_offsets.npy"
    np.save(p, np.load(p)[::-1].copy())


def _wrong_shape(d: Path) -> None:
    np.save(d / "shard-00000" / "camera_right.npy", np.zeros((3, 4, 4, 3), np.uint8))


def _shard_is_file(d: Path) -> None:
    shutil.rmtree(d / "shard-00000")
    (d / "shard-00000").write_text("x")


def _edit_records(edit):
    """Damage the first record of shard-00000/frames.json: edit(record) in place."""
    def damage(d: Path) -> None:
        p = d / S0 / "frames.json"
        doc = json.loads(p.read_text())
        edit(doc["frames"][0])
        p.write_text(json.dumps(doc))  # (json writes NaN and Infinity as bare words: not JSON)
    return damage


def _one_box(box):
    """A valid camera_right label set of one box `box` (so only the box's values are wrong)."""
    return lambda r: r["labels"].update(camera_right={"ids": [1], "labels": [1], "boxes": [box], "difficult": [False]})


def _object_size(size):
    """A valid objects set of one 3D box of `size` (so only the size is wrong)."""
    return lambda r: r["labels"].update(objects={"ids": [1], "center": [[10.0, 0.0, 1.0]], "size": [size]})


def _calibration(camera: str | None, field: str, value):
    """Set meta.calibration[camera][field] (or calibration[field] when camera is None) to `value`, or to
    value(old) when it is callable."""
    def edit(r):
        cal = r["meta"]["calibration"]
        where = cal if camera is None else cal[camera]
        where[field] = value(where[field]) if callable(value) else value
    return edit


def _scaled(T):  # the rotation doubled: not orthonormal
    return [[2 * x for x in row[:3]] + row[3:] for row in T[:3]] + T[3:]


def _mirrored(T):  # a reflection: orthonormal, determinant -1
    return [[-row[0]] + row[1:] for row in T[:3]] + T[3:]


def _sheared(T):
    return [T[0][:1] + [T[0][1] + 0.2] + T[0][2:]] + T[1:]


def _not_utf8(d: Path) -> None:
    p = d / S0 / "frames.json"
    p.write_bytes(p.read_bytes().replace(b'"junction"', b'"junc\xfftion"', 1))  # valid JSON bytes otherwise


def _extra_shard(d: Path) -> None:
    shutil.copytree(d / "shard-00001", d / "shard-00002")


def _fewer_shards(d: Path) -> None:
    """A manifest that lists shard-00000 only (of the two folders), consistent in itself."""
    m = json.loads((d / "manifest.json").read_text())
    m["shards"], m["frames"] = m["shards"][:1], [f for f in m["frames"] if f["shard"] == S0]
    (d / "manifest.json").write_text(json.dumps(m, indent=1))


def _lidar_point(value: float, row: int = 5):
    def damage(d: Path) -> None:
        p = d / S0 / "lidar_points.npy"
        a = np.load(p)
        a[row, 1] = value
        np.save(p, a)
    return damage


def _array_of_shape(name: str, frame_shape: tuple):
    def damage(d: Path) -> None:
        np.save(d / S0 / f"{name}.npy", np.zeros((1, *frame_shape), np.uint8))  # one frame, like the shard
    return damage


S0 = "shard-00000"
NAN, INF = float("nan"), float("inf")
# damage name -> (what the error line must name, how to damage a copy of the fixture dataset)
DAMAGES = {
    "manifest_is_a_list": ("manifest.json", lambda d: _write(d / "manifest.json", "[]")),
    "manifest_is_a_number": ("manifest.json", lambda d: _write(d / "manifest.json", "3")),
    "manifest_invalid_json": ("manifest.json", lambda d: _write(d / "manifest.json", "{not json")),
    "manifest_truncated": ("manifest.json", _truncate("manifest.json")),
    "manifest_binary": ("manifest.json", lambda d: (d / "manifest.json").write_bytes(bytes(range(256)))),
    "manifest_missing": ("manifest.json", _remove("manifest.json")),
    "manifest_frames_not_a_list": ("manifest.json", _edit_manifest(lambda m: m.update(frames="x"))),
    "manifest_shards_empty": ("manifest.json", _edit_manifest(lambda m: m.update(shards=[]))),
    "manifest_shard_frames_a_string": ("manifest.json", _edit_manifest(lambda m: m["shards"][0].update(frames="1"))),
    "manifest_shard_name_escapes": ("manifest.json", _edit_manifest(lambda m: m["shards"][0].update(name="../../etc"))),
    "manifest_frame_index_out_of_range": ("manifest.json", _edit_manifest(lambda m: m["frames"][0].update(index=7))),
    "manifest_frame_of_unknown_shard": ("manifest.json", _edit_manifest(lambda m: m["frames"][0].update(shard="shard-09999"))),
    "manifest_config_a_list": ("manifest.json", _edit_manifest(lambda m: m.update(config=[]))),
    "frames_json_invalid": ("frames.json", lambda d: _write(d / S0 / "frames.json", '{"frames": [')),
    "frames_json_a_list": ("frames.json", lambda d: _write(d / S0 / "frames.json", "[]")),
    "frames_json_frames_a_string": ("frames.json", lambda d: _write(d / S0 / "frames.json", '{"frames": "x"}')),
    "frames_json_frame_count": ("frames.json", lambda d: _write(d / S0 / "frames.json", '{"frames": []}')),
    "frames_json_meta_a_number": ("frames.json", lambda d: _write(d / S0 / "frames.json",
                                                                  '{"frames": [{"meta": 1, "labels": {}}]}')),
    "frames_json_missing": ("frames.json", _remove(f"{S0}/frames.json")),
    "npy_truncated": ("camera_right.npy", _truncate(f"{S0}/camera_right.npy")),
    "npy_header_flipped": ("camera_right.npy", _flip(f"{S0}/camera_right.npy", slice(10, 40))),
    "npy_magic_flipped": ("camera_right.npy", _flip(f"{S0}/camera_right.npy", slice(0, 6))),
    "npy_empty": ("camera_right.npy", _truncate(f"{S0}/camera_right.npy", 0.0)),
    "npy_missing": ("camera_right.npy", _remove(f"{S0}/camera_right.npy")),
    "npy_wrong_frame_count": ("camera_right.npy", _wrong_shape),
    "points_truncated": ("lidar_points.npy", _truncate(f"{S0}/lidar_points.npy", 0.9)),
    "offsets_reversed": ("lidar_offsets.npy", _reversed_offsets),
    "shard_missing": (S0, _remove(S0)),
    "shard_is_a_file": (S0, _shard_is_file),
    # labels and calibration: structure, types, finite numbers; arrays against the sensor profile
    "labels_without_a_camera": ("frames.json", _edit_records(lambda r: r["labels"].pop("camera_right"))),
    "labels_without_boxes": ("frames.json", _edit_records(lambda r: r["labels"]["camera_right"].pop("boxes"))),
    "labels_without_objects": ("frames.json", _edit_records(lambda r: r["labels"].pop("objects"))),
    "labels_a_list": ("frames.json", _edit_records(lambda r: r["labels"].update(bev=[]))),
    "boxes_a_string": ("frames.json", _edit_records(lambda r: r["labels"]["bev"].update(boxes="0,0,1,1"))),
    "box_of_strings": ("frames.json", _edit_records(_one_box(["0", "0", "1", "1"]))),
    "box_of_three": ("frames.json", _edit_records(_one_box([0.0, 0.0, 1.0]))),
    "box_a_number": ("frames.json", _edit_records(_one_box(3.0))),
    "box_of_booleans": ("frames.json", _edit_records(_one_box([True, False, True, True]))),
    "label_columns_of_other_lengths": ("frames.json", _edit_records(
        lambda r: r["labels"]["camera_right"].update(ids=[1], labels=[1], boxes=[[1, 1, 2, 2]], difficult=[]))),
    "label_class_a_string": ("frames.json", _edit_records(
        lambda r: r["labels"]["camera_right"].update(ids=[1], labels=["car"], boxes=[[1, 1, 2, 2]], difficult=[0]))),
    "box_nan": ("frames.json", _edit_records(_one_box([NAN, 0.0, 10.0, 10.0]))),
    "box_inf": ("frames.json", _edit_records(_one_box([0.0, 0.0, INF, 10.0]))),
    "box_minus_inf": ("frames.json", _edit_records(_one_box([-INF, 0.0, 10.0, 10.0]))),
    "box_overflowing_number": ("frames.json", lambda d: _write(d / S0 / "frames.json", (d / S0 / "frames.json")
                                                               .read_text().replace('"labels":', '"x": 1e999, "labels":', 1))),
    "object_nan": ("frames.json", _edit_records(lambda r: r["labels"].update(objects={"ids": [1], "range_m": [NAN]}))),
    "calibration_nan": ("frames.json", _edit_records(lambda r: r["meta"]["calibration"]["camera_right"]["K"][0]
                                                     .__setitem__(0, NAN))),
    "calibration_inf": ("frames.json", _edit_records(lambda r: r["meta"]["calibration"]["ego_from_lidar"][0]
                                                     .__setitem__(3, INF))),
    "calibration_missing": ("frames.json", _edit_records(lambda r: r["meta"].pop("calibration"))),
    "calibration_other_size": ("frames.json", _edit_records(lambda r: r["meta"]["calibration"]["camera_right"]
                                                            .update(width=100))),
    "manifest_nan": ("manifest.json", _edit_manifest(lambda m: m["config"].update(frame_rate_hz=NAN))),
    "camera_wrong_height": ("camera_right.npy", _array_of_shape("camera_right", (100, 336, 3))),
    "camera_wrong_width": ("camera_left.npy", _array_of_shape("camera_left", (188, 100, 3))),
    "camera_wrong_channels": ("camera_right.npy", _array_of_shape("camera_right", (188, 336, 1))),
    "camera_gray": ("camera_right.npy", _array_of_shape("camera_right", (188, 336))),
    "lidar_bev_wrong_size": ("lidar_bev.npy", _array_of_shape("lidar_bev", (128, 128, 3))),
    "radar_polar_wrong_size": ("radar_polar.npy", _array_of_shape("radar_polar", (400, 100))),
    "radar_bev_with_channels": ("radar_bev.npy", _array_of_shape("radar_bev", (256, 256, 3))),
    "fwd_lidar_wrong_size": ("fwd_lidar.npy", _array_of_shape("fwd_lidar", (94, 168, 3))),
    # (issue 38) what `verify` once passed and the readers once took
    "frames_json_not_utf8": ("frames.json", _not_utf8),
    "shard_not_in_manifest": ("shard-00002", _extra_shard),
    "manifest_lists_fewer_shards": ("shard-00001", _fewer_shards),
    "context_unknown": ("frames.json", _edit_records(lambda r: r["meta"].update(context="atlantis"))),
    "context_not_canonical": ("frames.json", _edit_records(lambda r: r["meta"].update(context="Junction"))),
    "context_disagrees_with_manifest": ("frames.json", _edit_records(lambda r: r["meta"].update(context="fog"))),
    "manifest_context_unknown": ("manifest.json", _edit_manifest(lambda m: m["frames"][0].update(context="atlantis"))),
    "manifest_shard_context_unknown": ("manifest.json",
                                       _edit_manifest(lambda m: m["shards"][0].update(context="atlantis"))),
    "lidar_points_nan": ("lidar_points.npy", _lidar_point(NAN)),
    "lidar_points_inf": ("lidar_points.npy", _lidar_point(INF, row=-1)),
    # (issue 51) box geometry and calibration that once gave wrong results with exit 0
    "box_far_outside_the_image": ("frames.json", _edit_records(_one_box([-5000.0, 10.0, 99999.0, 20.0]))),
    "box_inverted": ("frames.json", _edit_records(_one_box([50.0, 10.0, 40.0, 20.0]))),
    "bev_box_outside_the_grid": ("frames.json", _edit_records(lambda r: r["labels"].update(
        bev={"ids": [1], "labels": [1], "boxes": [[10.0, 10.0, 900.0, 20.0]], "difficult": [False]}))),
    "object_of_zero_width": ("frames.json", _edit_records(_object_size([4.0, 0.0, 1.5]))),
    "object_of_negative_height": ("frames.json", _edit_records(_object_size([4.0, 1.8, -1.5]))),
    "camera_matrix_zero": ("frames.json", _edit_records(_calibration("camera_right", "K", [[0.0] * 3] * 3))),
    "camera_matrix_rank_deficient": ("frames.json", _edit_records(
        _calibration("camera_left", "K", [[168.9, 0.0, 168.0], [168.9, 0.0, 168.0], [0.0, 0.0, 1.0]]))),
    "camera_matrix_lower_triangle": ("frames.json", _edit_records(
        _calibration("camera_right", "K", [[168.9, 0.0, 168.0], [0.0, 168.9, 94.0], [0.3, 0.0, 1.0]]))),
    "ego_from_camera_scaled": ("frames.json", _edit_records(_calibration("camera_right", "ego_from_camera", _scaled))),
    "ego_from_camera_mirrored": ("frames.json", _edit_records(_calibration("camera_left", "ego_from_camera", _mirrored))),
    "ego_from_camera_last_row": ("frames.json", _edit_records(
        _calibration("camera_right", "ego_from_camera", lambda T: T[:3] + [[0.0, 0.0, 1.0, 1.0]]))),
    "ego_from_lidar_sheared": ("frames.json", _edit_records(_calibration(None, "ego_from_lidar", _sheared))),
    "manifest_unknown_key": ("manifest.json", _edit_manifest(lambda m: m.update(notes="x" * 1_000_000))),
}


def _save_torch(rel: str, obj):
    def damage(d: Path) -> None:
        import torch

        torch.save(obj() if callable(obj) else obj, d / rel)
    return damage


def _foreign_weights():
    import torch

    return {"model": {"encoder.weight": torch.zeros(3, 3)}, "optimizer": {}, "epoch": 1, "step_in_epoch": 0,
            "global_step": 1, "torch_rng": torch.get_rng_state()}


# damaged runs: name -> (what the error line must name, the damage, whether `train --out RUN` and
# `--init-from RUN` read the damaged file: they read checkpoint.pt only)
RUN_DAMAGES = {
    "checkpoint_truncated": ("checkpoint.pt", _truncate("checkpoint.pt"), True),
    "checkpoint_truncated_end": ("checkpoint.pt", _truncate("checkpoint.pt", 0.999), True),
    "checkpoint_empty": ("checkpoint.pt", _truncate("checkpoint.pt", 0.0), True),
    "checkpoint_text": ("checkpoint.pt", lambda d: _write(d / "checkpoint.pt", "not a checkpoint\n"), True),
    "checkpoint_a_list": ("checkpoint.pt", _save_torch("checkpoint.pt", [1, 2, 3]), True),
    "checkpoint_other_weights": ("checkpoint.pt", _save_torch("checkpoint.pt", _foreign_weights), True),
    "epoch_truncated": ("epoch-001.pt", _truncate("epoch-001.pt"), False),
}


# ---------------------------------------------------------------------------------------------
# the parser, walked


def commands(parser: argparse.ArgumentParser, prefix: tuple = ()):
    """(command words, its parser) for every leaf command, nested ones (bench sim) included."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            seen = set()
            for name, sub in action.choices.items():
                if id(sub) not in seen:  # aliases share a parser
                    seen.add(id(sub))
                    yield from commands(sub, prefix + (name,))
            return
    yield prefix, parser


def value_actions(parser):
    return [a for a in parser._actions if not isinstance(a, argparse._HelpAction) and a.nargs != 0
            and not isinstance(a, argparse._SubParsersAction)]


def kind(action) -> str | None:
    return getattr(action.type, "kind", None)


def valid_value(action, world) -> str:
    """A valid value for a required argument, from its kind."""
    k = kind(action)
    box = world["box"]
    if k == "dataset":
        return str(world["data"])
    if k == "run":
        return str(world["run"])
    if k == "out_file":
        return str(box / "new" / ("out" + (action.type.suffixes[0] if action.type.suffixes else ".png")))
    if k in ("out_dir", "cache_dir"):
        return str(box / "new_dir")
    if k == "out_path":
        return str(box / "new" / "out.png")
    if k == "study_config":
        return "tiny"
    if k == "in_file":  # an existing file (a command reads what it holds after parsing)
        return str(world["root"] / "a_file")
    if k == "predictions":
        return str(world["predictions"])
    if action.choices:
        return str(list(action.choices)[0])
    for opt in action.option_strings:
        if opt in EXAMPLES:
            return EXAMPLES[opt]
    raise AssertionError(f"no valid example for {action.option_strings or action.dest}: give it a typed kind "
                         "(study.cli) or add it to EXAMPLES in tests/study/test_fuzz.py")


def argv_with(words, parser, world, action=None, value=None) -> list[str]:
    """The command with every required argument valid, and `action` given `value` (None: left out)."""
    argv, positional = list(words), []
    for a in value_actions(parser):
        if a is action:
            if value is not None and not a.option_strings:
                positional.append(value)
            continue
        if not a.option_strings:
            positional.append(valid_value(a, world))
        elif a.required:
            argv += [a.option_strings[0], valid_value(a, world)]
    if action is not None and action.option_strings and value is not None:
        opt = action.option_strings[0]
        argv += [f"{opt}={value}"] if value.startswith("-") else [opt, value]
    return argv + positional


def base_argv(words, parser, world, skip=None) -> list[str]:
    return argv_with(words, parser, world, skip, None)


PATH_KINDS = ("out_file", "out_path", "out_dir", "cache_dir", "in_file", "study_config", "dataset", "run")


def bad_paths(world, suffix: str = "") -> list[str]:
    """Paths no command can use, for every path kind: a file name over 255 bytes (the OS says
    ENAMETOOLONG on any look at it), and a symbolic link loop, as the path and on its way."""
    links = world["root"] / "links"
    if suffix and not (links / f"loop{suffix}").is_symlink():
        os.symlink(f"loop{suffix}", links / f"loop{suffix}")
    return [str(world["box"] / ("x" * 300 + suffix)), str(world["box"] / ("\u00e9" * 200 + suffix)),
            str(links / f"loop{suffix}"), str(links / "loop" / f"x{suffix}")]


def bad_values(action, world) -> list[str]:
    """The bad values of an argument's kind (each must be refused)."""
    values = _bad_values(action, world)
    k = kind(action)
    if k in PATH_KINDS:
        suffixes = getattr(action.type, "suffixes", None) or ((".png",) if k == "out_path" else ())
        values += bad_paths(world, suffixes[0] if suffixes else "")
    if k in ("in_file", "study_config"):
        values.append(str(world["root"] / "latin1.yaml"))
    return values


def _bad_values(action, world) -> list[str]:
    root, box = world["root"], world["box"]
    t, k = action.type, kind(action)
    if action.choices is not None:
        return [BOGUS, ""]
    if k == "int":
        return ["abc", "", "1.5", "0x10", str(t.lo - 1), str(t.hi + 1), str(10**30)]
    if k == "float":
        return ["abc", "", "nan", "inf", "-inf", str(t.lo if t.lo_open else t.lo - 1), str(t.hi * 10)]
    if k == "ints":
        return ["", ",", f"{t.lo},,{t.lo}", f"{t.lo},{t.lo}", str(t.hi + 1), str(t.lo - 1), "x"]
    if k == "names":
        return ["", ",", " , ", "a,,b", "a,", "a,a", "rain+", "+fog", "city++rain", BOGUS]
    if k == "name":
        return ["", BOGUS, "a,b", "rain+", "+fog"]
    if k == "checkpoint":
        return ["", BOGUS, "epoch-1", "../checkpoint"]
    if k == "out_file":
        suffix = t.suffixes[0] if t.suffixes else ".png"
        values = ["", f"/proc/hydrabench-fuzz/x{suffix}", f"/sys/x{suffix}", str(root / "a_file" / f"x{suffix}"),
                  str(root / "empty_dir")]
        return values + ([str(box / "x.txt"), str(box / "x")] if t.suffixes else [])
    if k == "out_path":
        return ["", "/proc/hydrabench-fuzz/x.png", str(root / "a_file" / "x.png"), str(box / "x.txt")]
    if k == "out_dir":
        return ["", "/proc/hydrabench-fuzz/d", "/sys/d", str(root / "a_file"), str(root / "a_file" / "d"),
                str(root / "foreign")]
    if k == "cache_dir":
        return ["", "/proc/hydrabench-fuzz/d", "/sys/d", str(root / "a_file")]
    if k == "in_file":
        return ["", str(box / "missing.yaml"), str(root / "empty_dir")] + [
            str(root / f) for f in ("bad.yaml", "wrong_types.yaml", "list.yaml", "unknown_key.yaml")]
    if k == "study_config":
        return ["", BOGUS, str(box / "missing.yaml"), str(root / "empty_dir")] + [
            str(root / f) for f in ("bad.yaml", "wrong_types.yaml", "list.yaml", "unknown_key.yaml")]
    if k == "dataset":
        return ["", str(box / "missing"), str(root / "a_file"), str(root / "empty_dir"), str(world["run"])]
    if k == "run":
        return ["", str(box / "missing"), str(root / "a_file"), str(root / "empty_dir"), str(world["data"])]
    if t is int:
        return ["abc", "", "1.5", str(10**30)]
    if t is float:
        return ["abc", "", "nan", "inf"]
    if t is None:
        return [BOGUS, "", "rain+"]
    return ["abc", "", "-1", "nan"]  # a command's own type


def snapshot(root: Path) -> dict:
    """What a command could leave behind or change: every path (a file or directory created or
    removed anywhere), and the size and mtime of every file outside the damaged copies (which are
    many, and which no command writes to: their paths only, `_paths`)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        out[dirpath] = "dir"  # (its mtime changes when an output check probes it, by design)
        if dirpath == str(root) and "damaged" in dirnames:
            dirnames.remove("damaged")
            out.update(_paths(os.path.join(dirpath, "damaged")))
        for f in filenames:
            st = os.lstat(os.path.join(dirpath, f))  # (a link is not followed: links/loop loops)
            out[os.path.join(dirpath, f)] = (st.st_size, st.st_mtime_ns)
    return out


_LISTINGS: dict[str, tuple[dict, dict]] = {}


def _paths(top: str) -> dict:
    """Every directory and file under `top` ("dir" / "file"), listed again only when a directory's
    mtime changed (creating, removing or renaming an entry sets its directory's mtime): the damaged
    copies hold about 2,000 paths, and walking them twice per case was most of this suite's time."""
    known = _LISTINGS.get(top)
    if known is not None:
        mtimes, paths = known
        try:
            if all(os.stat(d).st_mtime_ns == m for d, m in mtimes.items()):
                return paths
        except OSError:  # a directory removed
            pass
    mtimes, paths = {}, {}
    for dirpath, _, filenames in os.walk(top):
        mtimes[dirpath] = os.stat(dirpath).st_mtime_ns
        paths[dirpath] = "dir"
        paths.update((os.path.join(dirpath, f), "file") for f in filenames)
    _LISTINGS[top] = (mtimes, paths)
    return paths


PARSER = None


def cli(argv) -> int:
    """study.cli.main with one parser for every case (building it costs 10 ms)."""
    global PARSER
    PARSER = PARSER or build_parser()
    return main(argv, PARSER)


def names_it(line: str, action, value: str) -> bool:
    """The error line names the argument (flag, name or metavar) or the bad value."""
    words = list(action.option_strings) + [action.dest, action.dest.replace("_", "-"), action.dest.replace("_", " ")]
    if action.metavar:
        words.append(str(action.metavar))
    if value.strip(" ,") and len(value.strip()) > 1:
        words += [value.strip(), Path(value.strip()).name]
    return any(w and w in line for w in words)


def check_refused(argv, capsys, world, needle=None, stdout_json=False, failures=None) -> str:
    """Run `argv` in-process and check the contract; returns the error line. Each broken rule is
    appended to `failures` (so one run lists every failing case), or asserted when it is None."""
    before = snapshot(world["root"])
    t0 = time.perf_counter()
    code = cli(argv)
    TRACKED.append((" ".join(argv), time.perf_counter() - t0))
    out, err = capsys.readouterr()
    after = snapshot(world["root"])
    lines = err.strip("\n").splitlines()
    what = f"hydrabench {' '.join(repr(a) if not a or ' ' in a else a for a in argv)}"
    problems = []
    if code != 2:
        problems.append(f"exit {code} (expected 2); stderr: {err[-300:]}")
    if "Traceback" in err:
        problems.append(f"traceback: {err[-1500:]}")
    elif len(lines) != 1 or not lines[0].startswith("hydrabench"):
        problems.append(f"{len(lines)} lines on stderr, expected one: {err[-500:]}")
    if stdout_json:
        try:
            ok = out.count("\n") == 1 and isinstance(json.loads(out), dict)
        except ValueError:
            ok = False
        if not ok:
            problems.append(f"stdout is not one JSON object: {out[:300]!r}")
    elif out:
        problems.append(f"wrote to stdout: {out[:300]!r}")
    new = sorted(set(after) - set(before))
    changed = sorted(p for p in before if after.get(p) != before[p])
    if new or changed:
        problems.append(f"left behind {new[:5]}, changed or removed {changed[:5]}")
    if needle is not None and len(lines) == 1 and not (needle(lines[0]) if callable(needle) else needle in lines[0]):
        problems.append(f"the line does not name what is wrong: {lines[0]}")
    for p in new[::-1]:  # clean up, so one failure does not cascade into the next cases
        shutil.rmtree(p, ignore_errors=True) if os.path.isdir(p) else os.unlink(p)
    if problems:
        msg = f"{what}: " + "; ".join(problems)
        if failures is None:
            raise AssertionError(msg)
        failures.append(msg)
    return lines[0] if lines else ""


def report(failures: list[str], tried: int) -> None:
    assert not failures, f"{len(failures)} of {tried} cases broke the contract:\n" + "\n".join(failures[:40])


@pytest.fixture()
def sandbox(world, monkeypatch):
    monkeypatch.chdir(world["box"])
    monkeypatch.setenv("HYDRABENCH_CACHE", str(world["root"] / "cache"))  # theory's default cache
    return world


# ---------------------------------------------------------------------------------------------
# the tests


def test_every_option_of_every_command_refuses_its_bad_values(sandbox, capsys):
    world = sandbox
    parser = build_parser()
    tried, failures = 0, []
    for words, p in commands(parser):
        for action in value_actions(p):
            for value in bad_values(action, world):
                argv = argv_with(words, p, world, action, value)
                check_refused(argv, capsys, world, needle=lambda line, a=action, v=value: names_it(line, a, v),
                              failures=failures)
                tried += 1
            if action.nargs in ("+", "*") and action.option_strings:  # list options: nothing, or a value twice
                first = (action.default or ["x"])[0]
                for values in ([], [str(first), str(first)]):
                    argv = base_argv(words, p, world) + [action.option_strings[0], *values]
                    check_refused(argv, capsys, world, needle=lambda line, a=action: names_it(line, a, ""),
                                  failures=failures)
                    tried += 1
    report(failures, tried)
    assert tried > 300, tried


def test_every_dataset_argument_refuses_damaged_datasets_naming_the_file(sandbox, capsys):
    world = sandbox
    tried, failures = 0, []
    for words, p in commands(build_parser()):
        for action in value_actions(p):
            if kind(action) != "dataset":
                continue
            for name, (culprit, _) in DAMAGES.items():
                copy = str(world["damaged"] / name)
                argv = argv_with(words, p, world, action, copy)
                # verify reports a damaged shard by its name; the readers name the file
                check_refused(argv, capsys, world, failures=failures,
                              needle=lambda line, c=culprit: c in line or (S0 in line and c != "manifest.json"))
                tried += 1
    report(failures, tried)
    assert tried >= 6 * len(DAMAGES), tried


def test_every_run_argument_refuses_damaged_checkpoints_naming_the_file(sandbox, capsys):
    """Truncated, empty, foreign checkpoints: every command taking a run (its RUN argument, with
    --checkpoint epoch-001 where it has one), `train --out RUN` resuming it and `train --init-from
    RUN` are refused before any work, naming the file, and change nothing (the run's config.json
    included: train must not rewrite it before it has read the checkpoint)."""
    world = sandbox
    tried, failures = 0, []
    parser = build_parser()
    for words, p in commands(parser):
        for action in value_actions(p):
            if kind(action) != "run":
                continue
            has_checkpoint = any(kind(a) == "checkpoint" for a in value_actions(p))
            for name, (culprit, _, _) in RUN_DAMAGES.items():
                copy = str(world["damaged_runs"] / name)
                argv = argv_with(words, p, world, action, copy)
                if has_checkpoint and culprit.startswith("epoch-"):
                    argv = argv[:len(words)] + ["--checkpoint", culprit[:-3]] + argv[len(words):]
                # the file, or the run (a command may first miss something else in it: a trained gate)
                check_refused(argv, capsys, world, failures=failures,
                              needle=lambda line, c=culprit, r=copy: c in line or r in line)
                tried += 1
    fixture = ["--branches", "camera_right", "--batch-size", "1", "--warmup-steps", "1", "--threads", "2",
               "--eval-frames", "1", *NARROW_ARGS]  # the fixture run's config: a resume reaches its checkpoint
    for name, (culprit, _, read_by_train) in RUN_DAMAGES.items():
        if not read_by_train:
            continue
        copy = str(world["damaged_runs"] / name)
        for argv in (["train", str(world["data"]), "--out", copy, "--epochs", "2", *fixture],
                     ["train", str(world["data"]), "--out", str(world["box"] / "new_run"), "--init-from", copy,
                      *fixture]):
            if "--init-from" in argv and name == "checkpoint_other_weights":
                continue  # (a warm start copies the tensors that match, none here: not an error)
            check_refused(argv, capsys, world, needle=culprit, failures=failures)
            tried += 1
    report(failures, tried)
    assert tried >= 5 * len(RUN_DAMAGES), tried


def test_generate_refuses_an_out_another_generate_is_writing(world, tmp_path, capsys):
    """Two generate runs into one --out: the second is refused with one line naming the first's
    PID, and changes nothing; once the first is done, the same command completes the dataset and
    leaves no lock file and no shard-*.tmp-PID/ behind."""
    out = tmp_path / "d"
    shutil.copytree(world["data"], out)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom pathlib import Path\nfrom sensors.dataset import output_lock\n"
         "with output_lock(Path(sys.argv[1])):\n    print('locked', flush=True)\n    sys.stdin.readline()\n", str(out)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[2],
        env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2])))
    argv = ["generate", "--out", str(out), "--contexts", "junction", "--frames-per-context", "2",
            "--sequence-length", "1", "--seed", "3"]
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = snapshot(out)
        TRACKED.append(("generate while another generate writes --out", 0.0))
        code = cli(argv)
        err = capsys.readouterr().err
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert f"PID {holder.pid}" in err and str(out) in err, err
        assert snapshot(out) == before
    finally:
        holder.communicate("\n", timeout=60)
    assert holder.returncode == 0
    assert cli(argv + ["--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["frames"] == 2 and r["frames_rendered"] == 0
    assert sorted(os.listdir(out)) == ["manifest.json", "shard-00000", "shard-00001"]


def test_generate_refuses_a_damaged_shard_in_its_out_and_leaves_no_partial_shard(world, tmp_path, capsys,
                                                                               monkeypatch):
    """A shard of --out that is a file, or a directory without frames.json, is refused by name before
    anything is written; a write that fails (here: a full disk at the commit) removes its
    shard-*.tmp-PID/ and the lock."""
    argv = ["--contexts", "junction", "--frames-per-context", "2", "--sequence-length", "1", "--seed", "3"]
    for name in ("shard_is_a_file", "frames_json_missing"):
        out = tmp_path / name
        shutil.copytree(world["damaged"] / name, out)
        before = snapshot(tmp_path)
        TRACKED.append((f"generate --out {name}", 0.0))
        code = cli(["generate", "--out", str(out), *argv])
        err = capsys.readouterr().err
        assert code == 2 and len(err.strip().splitlines()) == 1 and S0 in err and "Traceback" not in err, err
        assert snapshot(tmp_path) == before
    import errno

    import sensors.dataset

    def full_disk(tmp, final):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(sensors.dataset, "commit_shard", full_disk)
    out = tmp_path / "partial"
    shutil.copytree(world["data"], out)
    shutil.rmtree(out / "shard-00001")  # one shard left to render
    (out / "manifest.json").unlink()
    from sensors.generate import GenerateConfig, generate

    with pytest.raises(OSError, match="No space left"):
        generate(GenerateConfig(contexts=("junction",), frames_per_context=2, sequence_length=1, seed=3), out,
                 workers=1, progress=False)
    assert sorted(os.listdir(out)) == [S0]


def test_verify_json_reports_every_damage_on_stdout(sandbox, capsys):
    world = sandbox
    for name in [*DAMAGES, "pixel_flipped"]:
        copy = world["damaged"] / name
        if name == "pixel_flipped" and not copy.exists():
            shutil.copytree(world["data"], copy)
            _flip(f"{S0}/camera_right.npy", slice(-100, -90))(copy)  # only the checksum can tell
        check_refused(["verify", str(copy), "--json"], capsys, world, stdout_json=True)
        code = cli(["verify", str(copy), "--json"])
        out, _ = capsys.readouterr()
        r = json.loads(out)
        assert code == 2 and r["ok"] is False and r["problems"], (name, r)
    assert cli(["verify", str(world["data"]), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r == {"ok": True, "dir": str(world["data"]), "shards": 2, "frames": 2, "problems": []}


def test_unknown_flags_and_missing_arguments_are_named(sandbox, capsys):
    world = sandbox
    assert "--bogus" in check_refused(["--bogus"], capsys, world)
    assert "--bogus" in check_refused(["--bogus", "scenes"], capsys, world)
    check_refused([], capsys, world, needle="command")
    check_refused(["nonsense"], capsys, world, needle="nonsense")
    for words, p in commands(build_parser()):
        assert "--bogus" in check_refused(base_argv(words, p, world) + ["--bogus"], capsys, world)
        for a in value_actions(p):
            if a.required or not a.option_strings:  # leave it out
                argv = base_argv(words, p, world, skip=a)
                check_refused(argv, capsys, world, needle=lambda line, a=a: names_it(line, a, ""))
            elif a.nargs is None:  # the flag without its value
                check_refused(base_argv(words, p, world) + [a.option_strings[0]], capsys, world,
                              needle=lambda line, a=a: names_it(line, a, ""))


def test_help_explains_every_option_without_noise(capsys):
    parser = build_parser()
    for words, p in commands(parser):
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                continue
            assert a.help and len(a.help) > 3, f"hydrabench {' '.join(words)} {a.option_strings or a.dest}: no help"
        with pytest.raises(SystemExit) as exc:
            cli([*words, "--help"])
        assert exc.value.code == 0
        out = capsys.readouterr().out
        TRACKED.append((" ".join(words) + " --help", 0.0))
        assert "(default: None)" not in out and "(default: )" not in out, out
        flat = " ".join(out.split())
        for chunk in flat.split(" --")[1:]:
            assert chunk.count("(default:") <= 1 and not ("(default:" in chunk and "]" in chunk.split("(default:")[0][-3:]), \
                f"hydrabench {' '.join(words)}: doubled default in --{chunk[:120]}"


def test_entry_point_end_to_end_in_a_subprocess(world, tmp_path):
    """The module entry point in a fresh process, not main(): no traceback there either, nothing on stdout."""
    env = dict(os.environ, HYDRABENCH_CACHE=str(tmp_path / "cache"))
    cmd = [sys.executable, "-m", "study.cli"]
    cases = [  # each subprocess is a fresh interpreter (seconds on a loaded machine): keep them few
        (["train", str(world["damaged"] / "npy_truncated"), "--out", str(tmp_path / "run")], "camera_right.npy"),
    ]
    for argv, needle in cases:
        TRACKED.append(("subprocess " + " ".join(argv), 0.0))
        p = subprocess.run(cmd + argv, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
        lines = p.stderr.strip().splitlines()
        assert p.returncode == 2 and "Traceback" not in p.stderr and len(lines) == 1 and needle in lines[0], \
            (argv, p.returncode, p.stderr[-800:])
        assert p.stdout == ""
    assert sorted(os.listdir(tmp_path)) == [], os.listdir(tmp_path)


def test_generate_refuses_a_folder_of_other_files_and_duplicates(world, tmp_path, capsys):
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("x")
    for argv, needle in ((["--out", str(foreign)], "thesis.tex"),
                         (["--out", str(tmp_path / "d"), "--contexts", "fog,motorway+fog"], "twice"),
                         (["--out", str(tmp_path / "d"), "--contexts", "all", "--frames-per-context", "200000"],
                          "limit is 1000000"),
                         (["--out", str(tmp_path / "d"), "--sequence-length", "20", "--frame-rate", "0.001"],
                          "3600")):
        TRACKED.append(("generate " + " ".join(argv), 0.0))
        code = cli(["generate", *argv])
        err = capsys.readouterr().err
        assert code == 2 and needle in err and len(err.strip().splitlines()) == 1, (argv, err)
    assert sorted(os.listdir(tmp_path)) == ["mine"] and os.listdir(foreign) == ["thesis.tex"]


def test_train_on_a_one_sequence_dataset_writes_its_checkpoint_and_reports_no_map(world, tmp_path, capsys):
    """A refused train creates nothing, so the corrected command is not refused as 'a different
    config'. One sequence: no test split, so no mAP (None, not a crash), and the checkpoint and curves
    are written, readable by others (0644 under umask 022)."""
    one = tmp_path / "one"
    shutil.copytree(world["data"], one)
    m = json.loads((one / "manifest.json").read_text())
    m["shards"], m["frames"] = m["shards"][:1], [f for f in m["frames"] if f["shard"] == S0]
    (one / "manifest.json").write_text(json.dumps(m))
    shutil.rmtree(one / "shard-00001")
    run = tmp_path / "run"
    for bad in (["--branches", "camera_right,radar_bogus"], ["--branch-set", BOGUS], ["--profile", "paper"],
                ["--init-from", str(tmp_path / "nowhere")], ["--hflip", "0.5", "--branches", "camera_both"]):
        TRACKED.append(("train " + " ".join(bad), 0.0))
        code = cli(["train", str(one), "--out", str(run), *bad])
        err = capsys.readouterr().err
        assert code == 2 and len(err.strip().splitlines()) == 1 and not run.exists(), (bad, err)
    old = os.umask(0o022)
    try:
        code = cli(["train", str(one), "--out", str(run), "--branches", "camera_right", "--epochs", "1",
                     "--batch-size", "1", "--warmup-steps", "1", "--json"])
        out, err = capsys.readouterr()
        assert code == 0, err[-2000:]
        r = json.loads(out)
        assert r["train_frames"] == 1 and r["test_frames"] == 0
        assert r["last"]["map_fused"] is None and r["last"]["map_camera_right"] is None
        assert r["last"]["loss_camera_right"] > 0
        assert (run / "checkpoint.pt").exists() and (run / "epoch-001.pt").exists()
        assert (run / "curves.png").stat().st_mode & 0o777 == 0o644
        assert cli(["export-coco", str(one), "--out", str(tmp_path / "coco" / "labels.json")]) == 0
        assert (tmp_path / "coco" / "labels.json").stat().st_mode & 0o777 == 0o644
    finally:
        os.umask(old)


def test_progress_reaches_a_log_file(world, tmp_path, capsys, monkeypatch):
    """stderr is not a terminal here (captured): generate and scenes still report progress, as lines."""
    monkeypatch.setenv("HYDRABENCH_PROGRESS_S", "0")  # a line per update
    code = cli(["scenes", "--context", "junction", "--frames", "3", "--json"])
    out, err = capsys.readouterr()
    assert code == 0 and json.loads(out)["frames"] == 3
    assert [line.split(",")[0] for line in err.splitlines()] == [
        "scenes junction: 1/3 frame (33%)", "scenes junction: 2/3 frame (67%)", "scenes junction: 3/3 frame (100%)"]
    # (closing does not print the last line a second time)
    code = cli(["generate", "--out", str(tmp_path / "d"), "--contexts", "junction", "--frames-per-context", "2",
                 "--sequence-length", "1", "--seed", "3", "--json"])
    out, err = capsys.readouterr()
    assert code == 0 and json.loads(out)["frames"] == 2
    assert "generate: 1/2 frame (50%)" in err and "generate: 2/2 frame (100%)" in err
    # the same seed and config as the fixture: byte-identical shards
    for name in ("shard-00000", "shard-00001"):
        assert (tmp_path / "d" / name / "camera_right.npy").read_bytes() == \
            (world["data"] / name / "camera_right.npy").read_bytes()


def test_line_progress_prints_every_interval_and_at_the_end():
    import io

    from sim.progress import LineProgress

    buf = io.StringIO()
    bar = LineProgress(total=4, desc="work", unit="step", interval=3600.0, stream=buf)
    for _ in range(4):
        bar.update(1)
    bar.close()
    assert buf.getvalue() == ""  # a short job stays quiet
    bar = LineProgress(total=4, desc="work", unit="step", interval=0.0, stream=buf)
    bar.update(1)
    bar.set_postfix(loss="1.5")
    bar.update(3)
    bar.close()
    lines = buf.getvalue().splitlines()
    assert lines[0].startswith("work: 1/4 step (25%), 0 s elapsed, ~0 s left")
    assert lines[1].startswith("work: 4/4 step (100%)") and lines[1].endswith("loss=1.5")
    assert len(lines) == 2  # the end is not printed twice
    buf = io.StringIO()
    bar = LineProgress(total=4, desc="work", unit="step", interval=0.0, stream=buf)
    bar.update(1)
    bar.set_postfix(loss="0.5")  # changed since the last line: the end says so
    bar.close()
    lines = buf.getvalue().splitlines()
    assert len(lines) == 2 and lines[0].startswith("work: 1/4 step") and lines[1].endswith("loss=0.5")


def test_line_progress_of_a_resumed_job_times_only_its_own_steps(monkeypatch):
    """A run resumed at step 100 of 140 that takes 10 s per step has ~390 s left after its first
    step, not the ~4 s that counting the resumed steps as done in this bar's time would say."""
    import io

    import sim.progress as sp

    clock = [1000.0]
    monkeypatch.setattr(sp.time, "monotonic", lambda: clock[0])
    buf = io.StringIO()
    bar = sp.LineProgress(total=140, desc="epoch 1/3", unit="step", initial=100, interval=0.0, stream=buf)
    clock[0] += 10.0
    bar.update(1)
    assert buf.getvalue().splitlines()[-1] == "epoch 1/3: 101/140 step (72%), 10 s elapsed, ~390 s left"
    bar = sp.LineProgress(total=140, desc="e", unit="step", initial=100, interval=0.0, stream=buf)
    bar._emit()  # nothing done yet in this bar: no estimate rather than a wrong one
    assert buf.getvalue().splitlines()[-1] == "e: 100/140 step (71%), 0 s elapsed"


def test_gate_data_label_and_lidar_fog_bars_print_whole_lines_into_a_log(capsys, monkeypatch):
    """In a log file a tqdm bar is carriage returns on one line; these bars print whole lines."""
    from sim.progress import LineProgress
    from sim.progress import progress as progress_bar

    monkeypatch.setenv("HYDRABENCH_PROGRESS_S", "0")  # a line at every update
    bar = progress_bar(total=3, desc="gate data", enabled=True)  # as study.engine.gate_data makes its bar
    assert isinstance(bar, LineProgress)
    bar.update(2)
    bar.close()
    err = capsys.readouterr().err
    assert "\r" not in err and err.splitlines()[0].startswith("gate data: 2/3 it (67%)")
    for path in ("study/experiments/label_stats.py", "study/bench/lidar_fog.py", "study/engine/gate_data.py"):
        assert "from tqdm import" not in (Path(__file__).resolve().parents[2] / path).read_text(), path


# ---------------------------------------------------------------------------------------------
# issue 38, part 3: kinds of bad input found by a new user


def _hold_lock(out: Path, command: str) -> subprocess.Popen:
    """A process holding `command`'s output lock on `out` until a line arrives on its stdin."""
    repo = Path(__file__).resolve().parents[2]
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys\nfrom pathlib import Path\nfrom sensors.dataset import output_lock\n"
         "with output_lock(Path(sys.argv[1]), sys.argv[2]):\n    print('locked', flush=True)\n    sys.stdin.readline()\n",
         str(out), command],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=repo, env=dict(os.environ, PYTHONPATH=str(repo)))
    assert holder.stdout.readline().strip() == "locked"
    return holder


def test_study_config_is_checked_whole_before_its_first_stage(world, tmp_path, capsys):
    """A gate the evaluation uses but the gates stage does not train, a gate named twice, a
    train.init_from that names nothing or a damaged run: refused before the generate stage (with
    --until generate too: the config is checked whole), with no study folder."""
    import yaml

    from study.pipeline.config import PRESETS_DIR, study_config_from_dict

    tiny = yaml.safe_load((PRESETS_DIR / "tiny.yaml").read_text())

    def edited(**sections):
        doc = json.loads(json.dumps(tiny))
        for section, values in sections.items():
            doc.setdefault(section, {}).update(values)
        return doc

    cases = [  # (config, what the line must name)
        (edited(gates={"gates": ["deep"]}), "evaluate.hydra_gate"),  # (hydra_gate: attention, the default)
        (edited(gates={"gates": ["deep", "deep"]}, evaluate={"hydra_gate": "deep"}), "twice"),
        (edited(gates={"gates": ["deep"]}, evaluate={"hydra_gate": "deep"}), "evaluate.eco_gate"),
        (edited(gates={"gates": []}, evaluate={"hydra_gate": "deep", "eco_gate": "knowledge"}), "evaluate.hydra_gate"),
        (edited(train={"init_from": str(tmp_path / "nowhere")}), "train.init_from"),
        (edited(train={"init_from": str(world["damaged_runs"] / "checkpoint_truncated")}), "checkpoint.pt"),
    ]
    out = tmp_path / "study"
    for k, (doc, needle) in enumerate(cases):
        path = tmp_path / f"case{k}.yaml"
        path.write_text(yaml.safe_dump(doc))
        before = snapshot(tmp_path)
        TRACKED.append((f"study {needle} case {k}", 0.0))
        code = cli(["study", str(path), "--out", str(out), "--until", "generate"])
        captured = capsys.readouterr()
        lines = captured.err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and needle in lines[0] and "Traceback" not in captured.err, \
            (doc, captured.err[-1500:])
        assert captured.out == "" and not out.exists() and snapshot(tmp_path) == before
    # what the check lets through: knowledge needs no trained gate; an existing run to start from
    from study.pipeline.checks import check_study_config

    check_study_config(study_config_from_dict(edited(gates={"gates": []}, evaluate={
        "hydra_gate": "knowledge", "eco_gate": "knowledge"}, train={"init_from": str(world["run"])})))
    check_study_config(study_config_from_dict(edited(gates={"gates": ["deep"]}, evaluate={
        "hydra_gate": "deep", "eco_gate": "deep"})))


def test_train_refuses_an_out_another_train_is_writing(world, tmp_path, capsys):
    """Two train runs into one --out: the second is refused with one line naming the first's PID (the
    lock generate takes, on RUN/.train.lock), and changes nothing; once the first is done, the same
    command runs and leaves no lock behind."""
    run = tmp_path / "run"
    shutil.copytree(world["run"], run)
    argv = ["train", str(world["data"]), "--out", str(run), "--branches", "camera_right", "--epochs", "1",
            "--batch-size", "1", "--warmup-steps", "1", "--threads", "2", "--eval-frames", "1", *NARROW_ARGS]  # the fixture's run
    holder = _hold_lock(run, "train")
    try:
        before = snapshot(tmp_path)
        TRACKED.append(("train while another train writes --out", 0.0))
        code = cli(argv)
        err = capsys.readouterr().err
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert f"PID {holder.pid}" in err and str(run) in err and "train" in err, err
        assert snapshot(tmp_path) == before
    finally:
        holder.communicate("\n", timeout=60)
    assert holder.returncode == 0
    assert cli(argv) == 0, capsys.readouterr().err[-2000:]  # (epoch 1 of 1 is done: nothing to train)
    capsys.readouterr()
    assert not (run / ".train.lock").exists()


@pytest.mark.parametrize("stop", ["SIGINT to the group", "SIGTERM to the parent"])
def test_ctrl_c_to_generate_with_workers_prints_one_line(tmp_path, stop):
    """Ctrl-C in a terminal sends SIGINT to the whole process group, the pool's workers included:
    they print nothing (no ForkPoolWorker traceback), the command prints `hydrabench: interrupted`,
    exits 130 and leaves no partial shard and no lock. `kill PID` (SIGTERM to the parent alone, as a
    service manager stops it) is handled the same way: `hydrabench: terminated`, exit 143, and the
    parent stops its workers (they once lived on, finished their shards and printed BrokenPipe
    tracebacks); a rerun can take the output lock at once."""
    import queue
    import signal
    import threading

    from sensors.dataset import foreign_entries, output_lock

    repo = Path(__file__).resolve().parents[2]
    out = tmp_path / "d"
    env = dict(os.environ, HYDRABENCH_PROGRESS_S="0", PYTHONPATH=str(repo))
    argv = [sys.executable, "-m", "study.cli", "generate", "--out", str(out), "--contexts", "junction",
            "--frames-per-context", "48", "--sequence-length", "2", "--seed", "3", "--workers", "2"]
    # 24 shards: on a loaded machine the stderr line can reach the test late, and 6 shards were
    # once all done before the SIGINT came (exit 0); interrupted, it stops early whatever the size
    TRACKED.append((f"{stop} of generate --workers 2", 0.0))
    p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path, env=env,
                         start_new_session=True)  # its own process group, as a terminal's job
    lines: queue.Queue = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(line) for line in p.stderr], daemon=True)
    reader.start()
    err: list[str] = []
    try:
        deadline = time.monotonic() + 300
        while not any(line.startswith("generate: ") for line in err):  # a shard done: the workers render the next
            assert time.monotonic() < deadline and p.poll() is None, "".join(err)[-2000:]
            try:
                err.append(lines.get(timeout=1.0))
            except queue.Empty:
                pass
        workers = _children(p.pid)
        if stop.startswith("SIGINT"):
            os.killpg(p.pid, signal.SIGINT)
        else:
            os.kill(p.pid, signal.SIGTERM)
        code = p.wait(timeout=120)
        alive = [pid for pid in workers if _running(pid)]  # (the parent joins its workers before it exits)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        else:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)  # (workers of a failed run, so they outlive no test)
    reader.join(timeout=30)
    while not lines.empty():
        err.append(lines.get())
    text = "".join(err)
    want = (130, "hydrabench: interrupted") if stop.startswith("SIGINT") else (143, "hydrabench: terminated")
    assert (code, text.splitlines()[-1]) == want, (code, text[-2000:])
    for word in ("Traceback", "ForkPoolWorker", "KeyboardInterrupt", "BrokenPipe"):
        assert word not in text, text[-2000:]
    assert len(workers) >= 2 and not alive, (workers, alive)  # (the pool's two, and any helper of the parent)
    assert p.stdout.read() == ""
    left = sorted(os.listdir(out))
    assert all(name.startswith("shard-") and ".tmp-" not in name for name in left), left  # complete shards only
    assert foreign_entries(out) == []
    with output_lock(out, "generate"):  # what a rerun takes first: free at once
        pass


def _children(pid: int) -> list[int]:
    """The PIDs whose parent is `pid` (Linux /proc)."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(entry))
    return out


def _running(pid: int) -> bool:
    """A process that exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_evaluate_names_the_missing_epoch_and_the_epochs_there(sandbox, capsys):
    """`evaluate --checkpoint epoch-002` of a one-epoch run names the missing file and the epochs the
    run has (not "not a training run")."""
    world = sandbox
    for words, p in commands(build_parser()):
        if words == ("evaluate",):
            argv = base_argv(words, p, world) + ["--checkpoint", "epoch-002"]
            line = check_refused(argv, capsys, world)
            assert "epoch-002.pt" in line and "epoch-001" in line and "not a training run" not in line, line
            return
    raise AssertionError("no evaluate command")


def test_every_workers_option_has_the_one_bound(sandbox, capsys):
    """Every --workers (generation pools and DataLoader processes alike) stops at MAX_WORKERS: 10,000
    once started forking 10,000 data-loader processes on train, evaluate, compare and train-gate."""
    from study.engine.device import MAX_WORKERS

    world, seen = sandbox, []
    for words, p in commands(build_parser()):
        for action in value_actions(p):
            if "--workers" in action.option_strings:
                seen.append(" ".join(words))
                assert getattr(action.type, "hi", None) == MAX_WORKERS, (words, action.type)
                check_refused(argv_with(words, p, world, action, str(MAX_WORKERS + 1)), capsys, world,
                              needle="--workers")
    assert {"generate", "train", "evaluate", "compare", "train-gate", "study"} <= set(seen), seen


def test_an_unusable_cache_location_is_one_line_before_work(sandbox, capsys, monkeypatch):
    """A reference model is copied into hydrabench's cache: a HOME that cannot be written, or a
    HYDRABENCH_CACHE that names an unusable place, is refused with one line naming it (it was an
    85-line traceback)."""
    world = sandbox
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    for env in ({"HOME": "/proc/nohome", "HYDRABENCH_CACHE": None}, {"HYDRABENCH_CACHE": "/proc/hydrabench-cache"},
                {"HYDRABENCH_CACHE": str(world["root"] / "a_file")}, {"HYDRABENCH_CACHE": " "}):
        for k, v in env.items():
            monkeypatch.delenv(k) if v is None else monkeypatch.setenv(k, v)
        line = check_refused(["evaluate", "cpu-ref", str(world["data"])], capsys, world)
        assert "HYDRABENCH_CACHE" in line, (env, line)


def test_an_empty_home_puts_no_cache_at_the_file_system_root(world, tmp_path, capsys, monkeypatch):
    """An empty HOME once made the cache /.cache/hydrabench (38 MB at the file system's root): the
    command takes the account's home from the password database instead, as Python does without
    HOME, and a library caller of the cache is refused."""
    import pwd
    from types import SimpleNamespace

    from sim.errors import UserError
    from study.outputs import cache_root

    home = tmp_path / "home"
    monkeypatch.setattr(pwd, "getpwuid", lambda uid: SimpleNamespace(pw_dir=str(home)))
    for k in ("HYDRABENCH_CACHE", "XDG_CACHE_HOME"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("HOME", "")
    with pytest.raises(UserError, match="HOME is empty"):
        cache_root()
    root_before = sorted(os.listdir("/.cache")) if os.path.isdir("/.cache") else None
    TRACKED.append(("evaluate cpu-ref with HOME=''", 0.0))
    code = cli(["evaluate", "cpu-ref", str(world["data"]), "--branches", BOGUS])  # (refused after the copy)
    err = capsys.readouterr().err
    assert code == 2 and BOGUS in err, err
    assert (sorted(os.listdir("/.cache")) if os.path.isdir("/.cache") else None) == root_before
    assert [p.name.split("-")[0] for p in (home / ".cache" / "hydrabench" / "models").iterdir()] == ["cpu"]


def _disk_full_at(call: int):
    """Path.write_text that writes half of its text and then fails with ENOSPC on its `call`-th call."""
    import errno

    real, calls = Path.write_text, []

    def write_text(self, data, *args, **kwargs):
        calls.append(self)
        if len(calls) == call:
            real(self, data[: len(data) // 2], *args, **kwargs)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))
        return real(self, data, *args, **kwargs)

    return write_text


def _short_npy_write(path, array, *args, **kwargs):
    """np.save on a full disk: part of the file, then numpy's OSError without an errno."""
    Path(path).write_bytes(b"\x93NUMPY" + bytes(100))
    raise OSError(f"{array.nbytes} requested and 100 written")


def test_a_full_disk_during_generate_is_one_line_and_leaves_nothing_partial(world, tmp_path, capsys, monkeypatch):
    """The disk fills while a shard's first array is written (numpy's short write, as on a full
    tmpfs), while its frames.json is written (1st text write), or the manifest (3rd, after both
    shards): one line naming the file, exit 2, no partial shard, no partial manifest, no lock (it was
    a 26-line traceback); the complete shards are kept for the rerun. export-coco likewise."""
    argv = ["generate", "--contexts", "junction", "--frames-per-context", "2", "--sequence-length", "1", "--seed", "3"]
    for case, (target, name, fake), (culprit, kept) in (
            ("npy", (np, "save", _short_npy_write), (".npy", [])),
            ("frames", (Path, "write_text", _disk_full_at(1)), ("frames.json", [])),
            ("manifest", (Path, "write_text", _disk_full_at(3)), (".manifest.json.tmp", ["shard-00000", "shard-00001"]))):
        out = tmp_path / case
        TRACKED.append((f"generate with the disk full writing the {case}", 0.0))
        with monkeypatch.context() as m:
            m.setattr(target, name, fake)
            code = cli([*argv, "--out", str(out)])
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and "No space left on device" in lines[0], err[-2000:]
        assert culprit in lines[0], lines
        assert sorted(os.listdir(out)) == kept
    # a checkpoint: torch's archive writer says "unexpected pos" where the disk is full (measured on a
    # 3 MB tmpfs); asked while the partial file is there, the file system tells a full disk from a bug
    import errno

    import torch

    import study.outputs as outputs

    def unexpected_pos(obj, fh):
        fh.write(b"PK" + bytes(100))
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 704 vs 598")

    for full in (True, False):
        with monkeypatch.context() as m:
            m.setattr(torch, "save", unexpected_pos)
            m.setattr(outputs, "_nearly_full", lambda directory, full=full: full)
            with pytest.raises(OSError if full else RuntimeError) as caught:
                outputs.torch_save_atomic({}, tmp_path / "ckpt" / "checkpoint.pt")
        assert (caught.value.errno == errno.ENOSPC) if full else "unexpected pos" in str(caught.value)
        assert os.listdir(tmp_path / "ckpt") == []
    coco = tmp_path / "coco" / "labels.json"
    TRACKED.append(("export-coco with the disk full", 0.0))
    with monkeypatch.context() as m:
        m.setattr(Path, "write_text", _disk_full_at(1))
        code = cli(["export-coco", str(world["data"]), "--out", str(coco)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "No space left on device" in err, err[-2000:]
    assert not coco.parent.exists() or os.listdir(coco.parent) == []


def test_compare_refuses_a_plot_without_intervals_before_the_networks_run(sandbox, capsys, monkeypatch):
    """`compare --plot` needs intervals: with --bootstrap 0, or on frames without a box to find (every
    mAP undefined), it is refused before any network runs (it once worked 17 s first)."""
    import study.engine.gate_tables
    import study.engine.predictions

    world = sandbox
    empty = world["root"] / "no_boxes"
    if not empty.exists():
        shutil.copytree(world["data"], empty)
        for fj in empty.glob("shard-*/frames.json"):
            doc = json.loads(fj.read_text())
            for r in doc["frames"]:
                for frame in LABEL_SETS:
                    r["labels"][frame] = {"ids": [], "labels": [], "boxes": [], "difficult": []}
                r["labels"]["objects"] = {"ids": []}
            fj.write_text(json.dumps(doc))
        _rehash(empty)

    def ran(*args, **kwargs):
        raise AssertionError("the networks ran")

    monkeypatch.setattr(study.engine.gate_tables, "gate_pass", ran)
    monkeypatch.setattr(study.engine.predictions, "_pass", ran)  # compare's one pass over the frames
    plot = str(world["box"] / "p.png")
    for data, extra, needle in ((world["data"], ["--bootstrap", "0"], "--bootstrap"),
                                (empty, ["--bootstrap", "20"], "no box to find")):
        check_refused(["compare", str(world["run"]), str(data), "--plot", plot, *extra], capsys, world, needle=needle)


LABEL_SETS = ("camera_left", "camera_right", "bev")


def test_study_refuses_a_typo_before_importing_torch(tmp_path):
    """A misspelt preset or a missing config file is refused before the study's configs (and torch)
    are imported: 7-10 s on 2 cores before, well under one now."""
    repo = Path(__file__).resolve().parents[2]
    code = ("import sys\nfrom study.cli import main\n"
            "codes = [main(['study', spec, '--out', sys.argv[1]]) for spec in ('tinyy', sys.argv[1] + '.yaml')]\n"
            "print(codes, 'torch' in sys.modules)\n")
    TRACKED.append(("study tinyy / study missing.yaml (subprocess)", 0.0))
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "s")], capture_output=True, text=True, cwd=repo,
                       env=dict(os.environ, PYTHONPATH=str(repo)), timeout=120)
    assert r.stdout.strip() == "[2, 2] False", (r.stdout, r.stderr[-2000:])
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 2 and "'tinyy' is neither a preset" in lines[0] and "does not exist" in lines[1], lines
    assert not (tmp_path / "s").exists()


def test_zz_count_of_cases(capsys):
    """Runs last in this file: the number of cases the suite tried (see the README)."""
    with capsys.disabled():
        print(f"\nfuzz: {len(TRACKED)} cases tried ({', '.join(f'{n}: {c}' for n, c in CASES_BY_TEST.items())}), {sum(t for _, t in TRACKED):.1f} s in-process; slowest:")
        for case, sec in sorted(TRACKED, key=lambda c: -c[1])[:8]:
            print(f"  {sec:6.2f} s  {case[:150]}")
    # every case-trying test of the file ran (none skipped or deselected), and the total is theirs
    assert set(CASES_BY_TEST) == CONTRIBUTORS, sorted(CONTRIBUTORS ^ set(CASES_BY_TEST))
    assert len(TRACKED) == sum(CASES_BY_TEST.values())
    assert CASES_BY_TEST["test_generate_refuses_a_folder_of_other_files_and_duplicates"] == 4
    assert CASES_BY_TEST["test_train_on_a_one_sequence_dataset_writes_its_checkpoint_and_reports_no_map"] == 5
    assert CASES_BY_TEST["test_entry_point_end_to_end_in_a_subprocess"] == 1
    assert CASES_BY_TEST["test_study_config_is_checked_whole_before_its_first_stage"] == 6
    assert len(TRACKED) > 500
