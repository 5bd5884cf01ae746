"""Failure fixtures: every number a user types is checked, no bad value reaches the chain.

NaN and ±inf, booleans for numbers and numbers for booleans, empty rig files and absurd nesting,
in every parameter model, in rig files, in ``--set``/``--params``, in a recording's stored rig
and in a ``rig`` artifact. Each CLI case asserts exit code 2, one line naming the file, key,
value and what is allowed, no traceback, and that nothing was created or overwritten.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, get_args, get_origin

import numpy as np
import pytest
from scan_tables import make_rig, positions_scan

from scanpipe.artifacts import write_artifact
from scanpipe.errors import ParameterError, RecordingError, RigError
from scanpipe.params import (
    MAX_NESTING,
    Params,
    _scalar_kinds,
    apply_assignments,
    load_toml,
    parse_toml,
    validate,
)
from scanpipe.recording.reader import read_recording
from scanpipe.recording.writer import RecordingWriter
from scanpipe.rig import Pose, Rig, default_rig, load_rig, rig_table, rig_to_toml

CliRunner = Callable[..., Any]


def _all_models() -> list[type[Params]]:
    """Every parameter model scanpipe defines (stages, rig, simulator, recorder, demo)."""
    import scanpipe.acquire.recorder
    import scanpipe.demo
    import scanpipe.pointio
    import scanpipe.sim.options  # noqa: F401  (defines SimOptions)
    from scanpipe.pipeline import registry

    registry()
    found: list[type[Params]] = []
    todo = list(Params.__subclasses__())
    while todo:
        model = todo.pop()
        if model.__module__.startswith("scanpipe.") and model not in found:
            found.append(model)
        todo += model.__subclasses__()
    return sorted(found, key=lambda m: f"{m.__module__}.{m.__name__}")


def _leaf(annotation: Any) -> tuple[Any, int | None]:
    """The scalar annotation of a field and, for a tuple, how many items it holds (-1: any)."""
    args = [a for a in get_args(annotation) if a is not type(None)]
    if get_origin(annotation) is tuple:
        return args[0], (-1 if len(args) == 2 and args[1] is Ellipsis else len(args))
    if len(args) == 1 and get_origin(annotation) is not tuple:
        return _leaf(args[0])
    return annotation, None


def _fields(kind: str) -> Iterator[tuple[type[Params], str, int | None]]:
    for model in _all_models():
        for name, field in model.model_fields.items():
            leaf, items = _leaf(field.annotation)
            if _scalar_kinds(leaf) == {kind}:
                yield model, name, items


def _value(bad: Any, items: int | None) -> Any:
    return bad if items is None else [bad] * max(items, 1)


NUMBER_FIELDS = sorted(_fields("number"), key=lambda f: (f[0].__name__, f[1]))
BOOL_FIELDS = sorted(_fields("bool"), key=lambda f: (f[0].__name__, f[1]))


def test_the_sweep_covers_every_stage_and_the_rig() -> None:
    models = {m.__name__ for m, _, _ in NUMBER_FIELDS}
    assert {"Pose", "ScannerConfig", "MotorConfig", "CameraConfig", "VoxelParams",
            "PoissonParams", "AssembleParams", "TextureParams", "DecodeParams",
            "SimOptions"} <= models
    assert len(NUMBER_FIELDS) > 80 and len(BOOL_FIELDS) > 20


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf], ids=["nan", "inf", "-inf"])
def test_no_float_field_anywhere_takes_nan_or_inf(bad: float) -> None:
    """No parameter needs inf (there is no "unbounded" spelled inf); every one refuses it."""
    accepted = []
    for model, name, items in NUMBER_FIELDS:
        if model.model_fields[name].annotation in (int, int | None):
            continue  # an int cannot be nan to begin with
        try:
            validate(model, {name: _value(bad, items)}, "p.toml")
        except ParameterError as err:
            assert f"{name}" in str(err) and "nan and inf are not allowed" in str(err), str(err)
        else:
            accepted.append(f"{model.__name__}.{name}")
    assert accepted == []


def test_no_number_field_takes_a_boolean() -> None:
    accepted = []
    for model, name, items in NUMBER_FIELDS:
        try:
            validate(model, {name: _value(True, items)}, "p.toml")
        except ParameterError as err:
            # pulse_limit has its own message (it also says how to declare a slip ring).
            expected = "not a boolean" if name == "pulse_limit" else \
                "expected a number, not true/false"
            assert expected in str(err), str(err)
        else:
            accepted.append(f"{model.__name__}.{name}")
    assert accepted == []


def test_no_boolean_field_takes_a_number() -> None:
    accepted = []
    for model, name, _ in BOOL_FIELDS:
        for number in (1, 0, 1.0):
            try:
                validate(model, {name: number}, "p.toml")
            except ParameterError as err:
                assert f"{name} = {number}: expected true or false" in str(err), str(err)
            else:
                accepted.append(f"{model.__name__}.{name}={number}")
    assert accepted == []


def test_true_and_false_still_work_for_booleans_and_ints_for_floats() -> None:
    from scanpipe.stages.filter import FilterParams

    params = validate(FilterParams, {"voxel": {"enabled": True, "size_m": 1}})
    assert params.voxel.enabled is True and params.voxel.size_m == 1.0


def _nested(depth: int) -> Any:
    value: Any = 0.0
    for _ in range(depth):  # built without recursion, deeper than any stack
        value = [value]
    return value


def test_absurd_nesting_is_refused_before_pydantic_and_others_still_reported() -> None:
    with pytest.raises(ParameterError) as info:
        validate(Rig, {"scanner": {"mount": {"translation_m": _nested(100_000)},
                                   "scan_hz": math.nan}}, "rig.toml")
    text = str(info.value)
    assert "4 problems" in text  # the cut array holds one item of three: two are missing
    assert "scanner.mount.translation_m.0.0.0.…: nested more than 32 levels deep" in text
    assert "scanner.scan_hz = nan: nan and inf are not allowed" in text


def test_nesting_at_the_limit_is_only_a_type_problem() -> None:
    with pytest.raises(ParameterError) as info:
        validate(Pose, {"translation_m": _nested(MAX_NESTING - 2)}, "p.toml")
    assert "nested more than" not in str(info.value)


def test_toml_nested_beyond_the_reader_is_one_line(tmp_path: Path) -> None:
    deep = "[" * 5000 + "]" * 5000
    with pytest.raises(ParameterError, match="nested too deeply to read"):
        parse_toml(f"a = {deep}", "x.toml")
    path = tmp_path / "p.toml"
    path.write_text(f"[filter.voxel]\nsize_m = {deep}\n")
    with pytest.raises(ParameterError) as info:
        load_toml(path)
    assert str(info.value).startswith(f"{path}: arrays or tables nested too deeply")
    with pytest.raises(ParameterError, match=r"filter\.voxel\.size_m: nested more than 32"):
        apply_assignments({}, [f"filter.voxel.size_m={deep}"])
    with pytest.raises(ParameterError, match=r"filter\.voxel\.size_m(\.0){6}\.…: nested more"):
        apply_assignments({}, ["filter.voxel.size_m=" + "[" * 40 + "]" * 40])


def test_not_utf8_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "p.toml"
    path.write_bytes(b"a = '\xff'\n")
    with pytest.raises(ParameterError, match="not UTF-8 text"):
        load_toml(path)


# --- rig files ---------------------------------------------------------------------------------

def _write(tmp_path: Path, text: str, name: str = "rig.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


BAD_RIGS = [
    ("[scanner.mount]\ntranslation_m = [nan, 0.0, 0.0]\n",
     "scanner.mount.translation_m.0 = nan: nan and inf are not allowed (allowed: a finite "
     "number ≥ -100 and ≤ 100)"),
    ("[scanner]\nscan_hz = inf\n",
     "scanner.scan_hz = inf: nan and inf are not allowed (allowed: a finite number > 0 and ≤ 100)"),
    ("[motor]\naccel_hz_per_s = -inf\n", "motor.accel_hz_per_s = -inf: nan and inf"),
    ("[[cameras]]\nid = 'c'\ndistortion = [0, 0, 0, 0, nan]\n",
     "cameras.0.distortion.4 = nan: nan and inf are not allowed"),
    ("[motor]\nbaudrate = true\n",
     "motor.baudrate = true: expected a number, not true/false (allowed: a whole number ≥ 50 and "
     "≤ 12000000)"),
    ("[scanner]\nbeam_step_deg = false\n",
     "scanner.beam_step_deg = false: expected a number, not true/false"),
    ("[scanner.mount]\nrotation_deg = [0, true, 0]\n",
     "scanner.mount.rotation_deg = [0, true, 0]: item 1: expected a number"),
    ("[motor]\ngear_ratio = 1e9\n",
     "motor.gear_ratio = 1000000000.0: out of range (allowed: a finite number ≥ 0.001 and "
     "≤ 100000)"),
    ("[motor]\nfull_step_deg = 90\ngear_ratio = 0.5\nunlimited_travel = true\n",
     "pulse step full_step_deg / gear_ratio = 90 / 0.5 = 180°; allowed: 1e-06° to 90°"),
    ("[motor]\naccel_hz_per_s = 1e9\n", "motor.accel_hz_per_s = 1000000000.0: out of range"),
    ("[motor]\nbaudrate = 20000000\n", "motor.baudrate = 20000000: out of range"),
    ("[motor]\nserial_url = ''\n", "motor.serial_url"),
    ("[scanner]\nhost = ''\n", "scanner.host"),
    ("[scanner.mount]\ntranslation_m = [0, 0, 250]\n",
     "scanner.mount.translation_m.2 = 250: out of range"),
    ("[[cameras]]\nid = 'c'\nfx = 5.0\n", "fx = 5 px over 1920 px gives a 179° field of view; "
                                        "allowed: 0.5° to 170°"),
    ("[[cameras]]\nid = 'c'\nfy = 2e6\n", "cameras.0.fy = 2000000.0: out of range"),
    ("[[cameras]]\nid = 'c'\nfy = 1e6\n", "cameras.0: fy = 1e+06 px over 1080 px gives a "
                                          "0.0619° field of view"),
    ("[[cameras]]\nid = 'c'\nwidth = 320\nheight = 240\nfx = 300.0\nfy = 300.0\n",
     "cameras.0: cx = 959.5 px is 800 px from the centre of the 320 px image; "
     "allowed: -0.5 to 319.5 (the image); intrinsics for another image size"),
    ("[[cameras]]\nid = 'c'\ncx = -12.5\n",
     "cameras.0: cx = -12.5 px is 972 px from the centre of the 1920 px image; allowed: -0.5 "
     "to 1919.5 (the image); a value near 0 is likely an offset from the image centre "
     "(Metashape's cx, cy)"),
    ("[[cameras]]\nid = 'c'\nwidth = 100000\n", "cameras.0.width = 100000: out of range"),
]


@pytest.mark.parametrize(("text", "needle"), BAD_RIGS, ids=[n[:30] for _, n in BAD_RIGS])
def test_cli_rig_check_refuses_with_one_line(cli: CliRunner, tmp_path: Path, text: str,
                                             needle: str) -> None:
    path = _write(tmp_path, text)
    result = cli("rig", "check", path)
    assert result.code == 2, result.err
    assert result.err.startswith(f"scanpipe: error: {path}: "), result.err
    assert needle in result.err
    assert result.err.count("\n") == 1 and "Traceback" not in result.err
    assert path.read_text() == text  # checked, not touched


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n"],
                         ids=["zero", "blank", "comment"])
def test_empty_rig_file_says_what_to_do(cli: CliRunner, tmp_path: Path, text: str) -> None:
    path = _write(tmp_path, text)
    result = cli("rig", "check", path)
    assert result.code == 2
    assert result.err == (f"scanpipe: error: {path}: the file is empty (no keys in it); write the "
                          f"default rig with `scanpipe rig init --force {path}` and edit it\n")
    assert path.read_text() == text
    with pytest.raises(RigError, match="the file is empty"):
        load_rig(path)


def test_deeply_nested_rig_file_is_one_line(cli: CliRunner, tmp_path: Path) -> None:
    for depth in (100, 5000):
        nested = "[" * depth + "]" * depth
        path = _write(tmp_path, f"[scanner.mount]\ntranslation_m = {nested}\n")
        result = cli("rig", "check", path)
        assert result.code == 2 and "Traceback" not in result.err
        assert "nested" in result.err and str(path) in result.err


def test_every_rig_problem_still_reported_at_once(tmp_path: Path) -> None:
    path = _write(tmp_path, "[scanner]\nscan_hz = nan\nmin_range_m = true\n[scanner.mount]\n"
                            "translation_m = [inf, 0, 0]\n[motor]\nbaudrate = false\n"
                            "gear_ratio = -inf\n")
    with pytest.raises(RigError) as info:
        load_rig(path)
    assert len(info.value.problems) == 5
    assert all(str(path) in line for line in str(info.value).splitlines()[1:])


def test_good_rigs_still_load(tmp_path: Path) -> None:
    assert load_rig(_write(tmp_path, rig_to_toml(default_rig()))) == default_rig()
    rig = load_rig(_write(tmp_path, "name = 'bench'\n[motor]\ngear_ratio = 1\npulse_limit = 250\n"
                                    "baudrate = 9600\n"))
    assert rig.motor.pulse_step_deg == 0.72 and rig.cameras == ()


# --- rig init ----------------------------------------------------------------------------------

@pytest.mark.parametrize("force", [False, True], ids=["plain", "force"])
def test_rig_init_onto_unwritable_places(cli: CliRunner, tmp_path: Path, force: bool) -> None:
    extra = ["--force"] if force else []
    folder = tmp_path / "folder"
    folder.mkdir()
    (folder / "keep.txt").write_text("keep")
    cases = [
        (Path("/proc/rig.toml"), "/proc/rig.toml: cannot be written ("),
        (folder, f"{folder}: is a folder; give a file name such as {folder / 'out.toml'}"),
        (tmp_path / "missing" / "rig.toml",
         f"{tmp_path / 'missing' / 'rig.toml'}: folder {tmp_path / 'missing'} does not exist; "
         "create it first"),
    ]
    for path, message in cases:
        result = cli("rig", "init", path, *extra)
        assert result.code == 2, (path, result.err)
        assert result.err.startswith(f"scanpipe: error: {message}"), result.err
        assert result.err.count("\n") == 1
    assert not (tmp_path / "missing").exists() and not Path("/proc/rig.toml").exists()
    assert sorted(p.name for p in folder.iterdir()) == ["keep.txt"]
    assert (folder / "keep.txt").read_text() == "keep"


def test_rig_init_never_overwrites_without_force(cli: CliRunner, tmp_path: Path) -> None:
    path = _write(tmp_path, "# my calibrated rig\nname = 'mine'\n")
    result = cli("rig", "init", path)
    assert result.code == 2
    assert result.err == f"scanpipe: error: {path}: already exists; pass --force to overwrite it\n"
    assert path.read_text() == "# my calibrated rig\nname = 'mine'\n"
    assert cli("rig", "init", path, "--force").code == 0
    assert load_rig(path) == default_rig()


# --- --set and --params ------------------------------------------------------------------------

@pytest.mark.parametrize(("assignment", "message"), [
    ("filter.voxel.size_m=inf",
     "--set: filter.voxel.size_m = inf: nan and inf are not allowed (allowed: a finite number "
     "> 0)"),
    ("filter.voxel.size_m=nan", "--set: filter.voxel.size_m = nan: nan and inf are not allowed"),
    ("filter.voxel.enabled=1", "--set: filter.voxel.enabled = 1: expected true or false, not a "
                               "number"),
    ("mesh.poisson.depth=true", "--set: mesh.poisson.depth = true: expected a number, not "
                                "true/false (allowed: a whole number ≥ 1 and ≤ 12)"),
    ("filter.voxel.size_m=" + "[" * 3000 + "]" * 3000,
     "--set: filter.voxel.size_m: nested more than 32 levels deep"),
])
def test_cli_run_refuses_bad_set_before_touching_anything(cli: CliRunner, tmp_path: Path,
                                                         assignment: str, message: str) -> None:
    result = cli("run", tmp_path / "rec.mcap", "-w", tmp_path / "work", "--set", assignment)
    assert result.code == 2
    assert result.err.startswith(f"scanpipe: error: {message}"), result.err
    assert result.err.count("\n") == 1 and "Traceback" not in result.err
    assert not (tmp_path / "work").exists()


def _assemble_inputs(folder: Path, rig: Rig | None = None) -> None:
    """Real ``profiles``, ``motor`` and ``rig`` artifacts of a small step scan."""
    good = make_rig(pulse_step_deg=2.0, beam_step_deg=10.0)
    tables = positions_scan(good, [0, 1, 2], np.full((3, 36), 3.0))
    if rig is not None:
        tables["rig"] = rig_table(rig)
    for name, table in tables.items():
        write_artifact(folder / f"{name}.parquet", table, {"key": name, "stage": "test"})


def test_cli_params_file_nested_too_deeply(cli: CliRunner, tmp_path: Path) -> None:
    deep = "[" * 3000 + "]" * 3000
    params = _write(tmp_path, f"[assemble]\nsettle_s = {deep}\n", "params.toml")
    _assemble_inputs(tmp_path / "dec")
    for args in (("run", tmp_path / "rec.mcap", "-w", tmp_path / "work"),
                 ("assemble", tmp_path / "dec", "--out", tmp_path / "work")):
        result = cli(*args, "--params", params)
        assert result.code == 2, result.err
        assert result.err == (f"scanpipe: error: {params}: arrays or tables nested too deeply "
                              "to read (no setting nests more than 32 levels)\n")
    assert not (tmp_path / "work").exists()


def test_cli_stage_command_refuses_inf_and_booleans(cli: CliRunner, tmp_path: Path) -> None:
    _assemble_inputs(tmp_path / "dec")
    for assignment, message in (
            ("settle_s=inf", "--set: settle_s = inf: nan and inf are not allowed"),
            ("keep_bad_checksum=0", "--set: keep_bad_checksum = 0: expected true or false")):
        result = cli("assemble", tmp_path / "dec", "--out", tmp_path / "work", "--set",
                     assignment)
        assert result.code == 2
        assert result.err.startswith(f"scanpipe: error: {message}"), result.err
    assert not (tmp_path / "work").exists()


# --- rigs inside recordings and artifacts ------------------------------------------------------

def _nan_rig() -> Rig:
    """A rig holding NaN calibration, as an older scanpipe or a hand-made file could store it
    (``model_copy`` does not validate, which is how such a value slips past the models)."""
    rig = default_rig()
    mount = Pose.model_construct(translation_m=(math.nan, 0.0, 0.0), rotation_deg=(0, 0, 0))
    return rig.model_copy(update={"scanner": rig.scanner.model_copy(update={"mount": mount})})


def test_recordings_stored_rig_goes_through_the_same_validation(cli: CliRunner,
                                                                tmp_path: Path) -> None:
    recording = tmp_path / "nan.mcap"
    with RecordingWriter(recording, _nan_rig(), {}) as writer:
        writer.write_motor_state(1_700_000_000_000_000_000, 1, 1, False, 0)
    with pytest.raises(RecordingError) as info:
        read_recording(recording).rig()
    assert f"{recording}: stored rig is invalid" in str(info.value)
    assert "scanner.mount.translation_m.0 = nan: nan and inf are not allowed" in str(info.value)
    # decode says so and passes the stored rig on; the stages that compute with it refuse it
    # (never the default rig in its place: that would be a silently wrong calibration) ...
    result = cli("decode", recording, "--out", tmp_path / "dec", "-q", "--json")
    assert result.code == 0, result.err
    assert "translation_m.0 = nan" in result.out and "pass a corrected rig" in result.out
    from scanpipe.artifacts import read_artifact
    from scanpipe.rig import rig_from_table

    with pytest.raises(RigError, match=r"translation_m\.0 = nan"):
        rig_from_table(read_artifact(tmp_path / "dec" / "rig.parquet")[0])
    result = cli("run", recording, "-w", tmp_path / "work", "-q")
    assert result.code == 2 and result.err.count("scanpipe: error:") == 1, result.err
    assert result.err.splitlines()[-1].startswith("scanpipe: error: rig artifact:")
    assert "translation_m.0 = nan" in result.err and "--rig" in result.err
    # ... and a corrected rig file given with --rig gets past it.
    good = _write(tmp_path, rig_to_toml(default_rig()))
    result = cli("run", recording, "-w", tmp_path / "work", "--rig", good, "--to", "decode", "-q")
    assert result.code == 0, result.err


def test_run_with_a_bad_rig_override_stops_before_any_stage(cli: CliRunner,
                                                           tmp_path: Path) -> None:
    recording = tmp_path / "r.mcap"
    with RecordingWriter(recording, default_rig(), {}) as writer:
        writer.write_motor_state(1_700_000_000_000_000_000, 1, 1, False, 0)
    rig = _write(tmp_path, "[scanner.mount]\ntranslation_m = [0.0, nan, 0.0]\n")
    result = cli("run", recording, "-w", tmp_path / "work", "--rig", rig, "-q")
    assert result.code == 2
    assert result.err == (f"scanpipe: error: {rig}: scanner.mount.translation_m.1 = nan: nan and "
                          "inf are not allowed (allowed: a finite number ≥ -100 and ≤ 100)\n")
    assert not (tmp_path / "work").exists()


def test_assemble_refuses_a_rig_artifact_with_nan_calibration(cli: CliRunner,
                                                              tmp_path: Path) -> None:
    rig = make_rig(pulse_step_deg=2.0, beam_step_deg=10.0)
    bad = rig.model_copy(update={"scanner": rig.scanner.model_copy(update={
        "mount": Pose.model_construct(translation_m=(0.0, math.inf, 0.0),
                                      rotation_deg=(0.0, 0.0, 0.0))})})
    _assemble_inputs(tmp_path / "dec", bad)
    result = cli("assemble", tmp_path / "dec", "--out", tmp_path / "asm", "-q")
    assert result.code == 2
    assert result.err == ("scanpipe: error: rig artifact: scanner.mount.translation_m.1 = inf: "
                          "nan and inf are not allowed (allowed: a finite number ≥ -100 and "
                          "≤ 100); run decode again or pass a corrected rig file with --rig\n")
    assert not (tmp_path / "asm" / "points.parquet").exists()
