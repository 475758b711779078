"""Dataset runs (``python -m holowarp.batch``, :mod:`holowarp.suite`): a tiny suite on Ray's
local runtime, the summary against the per-object files, failures, resume, bad suite files."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from holowarp.batch import main

TINY = """\
preset = "fast"
[overrides]
res = 16
scale_iters = 0.05
edge_length = 0.1
[synth]
views = 12
up_axis = "z"
[hull]
grid = 32
edge_length_fac = 0.1
max_surface_faces = 1000
[evaluate]
samples = 2000
volume_points = 2000
[simulate]
chamfer_samples = 2000
"""


def _tiny_meshes(folder: Path) -> None:
    import trimesh

    trimesh.creation.icosphere(subdivisions=2).export(folder / "ball.obj")
    trimesh.creation.box(extents=(1.0, 0.6, 0.4)).export(folder / "box.obj")


def _write(folder: Path, text: str, name: str = "suite.toml") -> Path:
    path = folder / name
    path.write_text(text)
    return path


def _json(path: Path):
    return json.loads(Path(path).read_text())


def _close(a, b) -> bool:
    return a is None and b is None or (a is not None and b is not None and math.isclose(a, b, rel_tol=1e-9))


@pytest.fixture(scope="module")
def ray_run(tmp_path_factory):
    """The CI suite: two tiny objects and one broken dataset, on Ray's local runtime."""
    pytest.importorskip("ray")
    d = tmp_path_factory.mktemp("suite")
    _tiny_meshes(d)
    (d / "empty_dataset").mkdir()
    suite = _write(d, TINY + '[[objects]]\nname = "ball"\nmesh = "ball.obj"\ngenus = 0\n'
                            '[[objects]]\nmesh = "box.obj"\ngenus = 1\n'
                            '[[objects]]\nname = "broken"\ndataset = "empty_dataset"\n')
    rc = main([str(suite), "--out", str(d / "out"), "--executor", "ray", "--workers", "2", "--quiet"])
    return d, suite, d / "out", rc


def test_ray_suite_runs_every_step_of_every_object(ray_run):
    _, _, out, rc = ray_run
    assert rc == 1  # one object failed
    for name in ("ball", "box"):
        st = _json(out / name / "status.json")
        assert st["status"] == "done", st["errors"]
        for f in ("data/transforms_test.json", "hull/report.json", "recon/report.json", "metrics.json",
                  "hull/metrics.json", "reference/gt.vtu", "sim/report.json", "hull/sim/report.json"):
            assert (out / name / f).is_file(), f


def test_a_failed_object_is_recorded_and_does_not_stop_the_others(ray_run):
    _, _, out, _ = ray_run
    st = _json(out / "broken" / "status.json")
    assert st["status"] == "failed" and st["step"] == "hull"
    assert "\n" not in st["error"] and "empty_dataset" in st["error"]
    assert {e["step"] for e in st["errors"]} == {"hull", "reconstruct"}
    s = _json(out / "summary.json")
    assert s["done"] == 2 and s["failed"] == 1
    for side in ("holowarp", "visual_hull"):
        assert s[side]["failure_rate"] == pytest.approx(1 / 3)
        assert s[side]["single_component_rate"] + s[side]["multi_component_rate"] + s[side]["failure_rate"] == \
            pytest.approx(1.0)
    assert "broken, step `hull`" in (out / "summary.md").read_text()


def test_summary_agrees_with_the_per_object_reports(ray_run):
    _, _, out, _ = ray_run
    s = _json(out / "summary.json")
    done = ("ball", "box")
    for side, metrics, sim in (("holowarp", "metrics.json", "sim"), ("visual_hull", "hull/metrics.json", "hull/sim")):
        m = {n: _json(out / n / metrics) for n in done}
        for key in ("chamfer_l1", "chamfer_l2", "recall", "hausdorff", "volume_iou", "min_dihedral_mean",
                    "aspect_ratio_mean", "inverted_ratio", "components"):
            assert _close(s[side]["mean"][key]["mean"], sum(m[n][key] for n in done) / 2), (side, key)
        sc = {n: _json(out / n / sim / "report.json")["sim_chamfer"] for n in done}
        assert set(s[side]["sim_chamfer"]) == {"0", "0.25", "0.5", "0.75", "1"}
        per_object = [sum(sc[n].values()) / len(sc[n]) for n in done]
        assert _close(s[side]["mean"]["sim_cd"]["mean"], sum(per_object) / 2)
        for t in sc["ball"]:
            assert _close(s[side]["sim_chamfer"][t]["mean"], (sc["ball"][t] + sc["box"][t]) / 2)
        single = sum(m[n]["components"] == 1 for n in done) / 3
        assert s[side]["single_component_rate"] == pytest.approx(single)
        assert s[side]["manifold_rate"] == pytest.approx(sum(bool(m[n]["manifold"]) for n in done) / 3)
    recon = {n: _json(out / n / "recon" / "report.json") for n in done}
    assert _close(s["holowarp"]["mean"]["psnr"]["mean"], sum(recon[n]["psnr_test"] for n in done) / 2)
    assert s["visual_hull"]["mean"]["psnr"]["n"] == 0  # the hull has no appearance
    rows = {r["name"]: r for r in s["per_object"]}
    # box was declared genus 1 (it is 0): the summary checks the genus against the suite.
    assert rows["ball"]["holowarp"]["genus_ok"] is True and rows["box"]["holowarp"]["genus_ok"] is False
    md = (out / "summary.md").read_text()
    assert "| | holowarp | visual hull |" in md and "| ball | done |" in md and "Sim-CD at 0.5 s" in md


def test_resume_keeps_done_objects_and_reruns_failed_ones(ray_run):
    d, suite, out, _ = ray_run
    before = {n: (out / n / "status.json").stat().st_mtime_ns for n in ("ball", "box")}
    rc = main([str(suite), "--out", str(out), "--executor", "local", "--resume", "--quiet"])
    assert rc == 1
    assert {n: (out / n / "status.json").stat().st_mtime_ns for n in ("ball", "box")} == before
    assert _json(out / "broken" / "status.json")["status"] == "failed"


def test_a_finished_run_is_not_overwritten_or_resumed_with_other_settings(ray_run, capsys):
    d, suite, out, _ = ray_run
    assert main([str(suite), "--out", str(out), "--executor", "local"]) == 2
    assert "--resume" in capsys.readouterr().err
    other = _write(d, suite.read_text().replace("scale_iters = 0.05", "scale_iters = 0.1"), "other.toml")
    assert main([str(other), "--out", str(out), "--executor", "local", "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "overrides.scale_iters: 0.05 -> 0.1" in err


def test_overrides_give_the_config_the_reconstruct_command_gives():
    from holowarp.reconstruct import build_parser, config_from_args
    from holowarp.suite import recon_config

    ov = {"res": 48, "scale_iters": 0.3, "edge_length": 0.07, "seed": 0, "no_continuous_opacity": True,
          "uniform_biharmonic": True, "single_stage_hc": True}
    args = build_parser().parse_args(["--out", "x", "--preset", "paper", "--res", "48", "--scale-iters", "0.3",
                                      "--edge-length", "0.07", "--seed", "0", "--no-continuous-opacity",
                                      "--uniform-biharmonic", "--single-stage-hc"])
    assert recon_config("paper", ov).to_dict() == config_from_args(args).to_dict()
    assert recon_config("fast", {"seed": 0}).seed == 0  # an explicit 0 is a value, not "not given"


def test_objects_get_their_resources_names_and_devices(tmp_path):
    from holowarp.suite import load_suite

    _tiny_meshes(tmp_path)
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "gt.obj").write_text((tmp_path / "ball.obj").read_text())
    s = load_suite(_write(tmp_path, '[resources]\nnum_cpus = 2\n[[objects]]\nmesh = "ball.obj"\n'
                                    '[[objects]]\ndataset = "ds"\nresources = { num_gpus = 1 }\n'))
    ball, ds = s.objects
    assert (ball.name, ball.num_cpus, ball.device, ball.gt) == ("ball", 2.0, "cpu", None)
    assert (ds.name, ds.num_cpus, ds.num_gpus, ds.device) == ("ds", 2.0, 1.0, "cuda")
    assert ds.gt == str(tmp_path / "ds" / "gt.obj")  # a dataset's own gt.obj is its ground truth


BAD_SUITES = [
    ("preset = 'fast'\n[[objects]\n", "not valid TOML"),
    ("color = 1\n[[objects]]\nmesh = 'ball.obj'\n", "suite.color: unknown key"),
    ("preset = 'slow'\n[[objects]]\nmesh = 'ball.obj'\n", "preset = 'slow'"),
    ("[overrides]\nresolution = 64\n[[objects]]\nmesh = 'ball.obj'\n", "[overrides].resolution: unknown key"),
    ("[overrides]\nres = 8\n[[objects]]\nmesh = 'ball.obj'\n", "overrides.res = 8"),
    ("[overrides]\nscale_iters = 0\n[[objects]]\nmesh = 'ball.obj'\n", "overrides.scale_iters = 0"),
    ("[overrides]\nseed = 'a'\n[[objects]]\nmesh = 'ball.obj'\n", "overrides.seed = 'a'"),
    ("[hull]\ngrid = 4\n[[objects]]\nmesh = 'ball.obj'\n", "hull.grid = 4"),
    ("[resources]\nnum_cpus = 0\n[[objects]]\nmesh = 'ball.obj'\n", "resources.num_cpus = 0"),
    ("preset = 'fast'\n", "objects: expected one or more"),
    ("[[objects]]\nmesh = 'nowhere.obj'\n", "nowhere.obj: no such file"),
    ("[[objects]]\ndataset = 'nowhere'\n", "objects[0].dataset"),
    ("[[objects]]\nmesh = 'ball.obj'\ngt = 'ball.obj'\n", "objects[0].gt: implied by mesh"),
    ("[[objects]]\nname = 'a'\nmesh = 'ball.obj'\ndataset = '.'\n", "objects[0]: give exactly one"),
    ("[[objects]]\nmesh = 'ball.obj'\ncolour = 1\n", "objects[0].colour: unknown key"),
    ("[[objects]]\nmesh = 'ball.obj'\ngenus = -1\n", "objects[0].genus = -1"),
    ("[[objects]]\nmesh = 'ball.obj'\n[[objects]]\nmesh = 'ball.obj'\n", "objects[1].name: 'ball' is already"),
    ("[[objects]]\nname = 'a/b'\nmesh = 'ball.obj'\n", "objects[0].name = 'a/b'"),
]


@pytest.mark.parametrize("text, expected", BAD_SUITES, ids=[e for _, e in BAD_SUITES])
def test_bad_suite_files_fail_with_one_line_naming_the_file_and_key(tmp_path, capsys, text, expected):
    _tiny_meshes(tmp_path)
    suite = _write(tmp_path, text)
    assert main([str(suite), "--out", str(tmp_path / "out"), "--executor", "local"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert str(suite) in err and expected in err, err
    assert not (tmp_path / "out").exists()  # nothing was done


def test_bad_output_folder_and_arguments_fail_before_any_work(tmp_path, capsys):
    _tiny_meshes(tmp_path)
    suite = _write(tmp_path, "[[objects]]\nmesh = 'ball.obj'\n")
    (tmp_path / "file").write_text("x")
    assert main([str(suite), "--out", str(tmp_path / "file"), "--executor", "local"]) == 2
    assert "--out" in capsys.readouterr().err
    assert main([str(suite), "--out", str(tmp_path / "o"), "--executor", "local", "--workers", "2"]) == 2
    assert "--workers 2" in capsys.readouterr().err
    assert main([str(suite), "--out", str(tmp_path / "o"), "--executor", "local", "--ray-address", "x:1"]) == 2
    assert "--ray-address" in capsys.readouterr().err
    assert main([str(tmp_path / "missing.toml"), "--out", str(tmp_path / "o")]) == 2
    assert "missing.toml: no such file" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_reconstruct_alone_raises_the_childs_own_error(tmp_path):
    """The dataset runs reconstruct each object in a fresh interpreter; a bad input still
    comes back as holowarp's error, with its message, not as a bare exit status."""
    from holowarp.config import preset
    from holowarp.pipeline import ReconstructionError, reconstruct_alone

    with pytest.raises(ReconstructionError, match="missing: no such folder"):
        reconstruct_alone(tmp_path / "missing", tmp_path / "out", config=preset("fast"), progress=False)
