"""``scan3d tune``: the capture assistant on the virtual rig, through ``appliance.cli.main``.

It picks one exposure on the default scene and at most three on the dark-and-shiny scene (albedo patches
0.03-0.95 and a glossy sphere whose highlight peaks at 8x the white level); the exposures it writes, rendered
and decoded with ``scan3d decode``, reach issue 25's completeness. ``--apply`` goes through validation and an
atomic write, keeping the file's comments.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from appliance import cli
from appliance.config import AppConfig, load_config
from appliance.output.ply import read_ply_vertices
from appliance.procedures.tune import Probe, TuneChoice, with_exposures, with_setting

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests" / "accuracy"))
from hard_scenes import capture, decode, scene_config, scene_text  # noqa: E402


def _tune(*args: object) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = cli.main(["tune", *[str(a) for a in args]])
    return rc, out.getvalue()


def _choice(text: str) -> list[int]:
    m = re.search(r"choice: sequence.exposures_us = \[([0-9, ]+)\]", text)
    assert m, text
    return [int(x) for x in m.group(1).split(",")]


def test_default_scene_needs_one_exposure(tmp_path: Path) -> None:
    # the configuration's one-camera rig (see its comments); the two-camera default asks a second exposure
    # for cam1's darker side (the projector is 380 mm from it)
    doc = yaml.safe_load((REPO / "config" / "appliance.yaml").read_text())
    del doc["cameras"]["cam1"], doc["virtual_rig"]["cameras"]["cam1"]
    doc["reconstruction"]["mode"] = "projector"
    (tmp_path / "one.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    rc, text = _tune("--config", tmp_path / "one.yaml")
    print(text)
    assert rc == 0, text
    assert _choice(text) == [10_000]
    assert "cannot recover" in text and "expected scan time" in text


@pytest.fixture(scope="module")
def dark_shiny(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    folder = tmp_path_factory.mktemp("tune")
    path = folder / "dark.yaml"
    path.write_text("# the dark-and-shiny scene\n" + scene_text("dark_shiny"))
    rc, text = _tune("--config", path, "--time-budget-ms", 6000, "--apply")
    print(text)
    assert rc == 0, text
    exposures = load_config(path).sequence.exposures_us
    rig = capture(scene_config("dark_shiny"), folder, "hdr", exposures)
    stats = decode(folder, "hdr", rig)[0]
    print(stats.line())
    return {"path": path, "text": text, "exposures": exposures, "stats": stats, "stats_folder": folder, "rig": rig}


def test_dark_and_shiny_gets_at_most_three_exposures_written_to_the_config(dark_shiny: dict[str, object]) -> None:
    exposures = dark_shiny["exposures"]
    assert isinstance(exposures, tuple) and 2 <= len(exposures) <= 3
    assert list(exposures) == _choice(str(dark_shiny["text"]))
    path = dark_shiny["path"]
    assert isinstance(path, Path)
    saved = path.read_text()
    assert saved.startswith("# the dark-and-shiny scene\n") and "chosen by scan3d tune" in saved
    assert "written: " in str(dark_shiny["text"])


def test_the_chosen_exposures_reconstruct_the_dark_patches(dark_shiny: dict[str, object]) -> None:
    # a pixel beside a patch that clipped comes from the brightest pass that did not clip it; its code is
    # corrected for the albedo edge from the fused white level (measured: 98.1 %, dark patches 98.5 %; with
    # the rule that a pixel needs 8 unclipped neighbours instead, 93.4 % / 89.5 %)
    s = dark_shiny["stats"]
    assert s.completeness >= 0.97, s.line()  # type: ignore[attr-defined]
    assert s.dark_completeness >= 0.95, s.line()  # type: ignore[attr-defined]


def test_the_chosen_exposures_keep_sigma_honest(dark_shiny: dict[str, object]) -> None:
    # measured 0.000 % beyond 5 sigma, |err|/sigma RMS 0.87; without the albedo-edge correction 1.26 %, 1.96
    s = dark_shiny["stats"]
    assert s.over_5sigma <= 1e-3, s.line()  # type: ignore[attr-defined]
    assert 0.7 <= s.z_rms <= 1.4, s.line()  # type: ignore[attr-defined]
    assert s.over_1mm <= 2e-3, s.line()  # type: ignore[attr-defined]  # measured 0.102 % (1.107 % uncorrected)


@pytest.fixture(scope="module")
def default_rms(dark_shiny: dict[str, object]) -> float:
    """RMS (mm) of the default scene with the default sequence (periods [16, 8])."""
    folder = dark_shiny["stats_folder"]
    assert isinstance(folder, Path)
    rms = decode(folder, "def", capture(scene_config("default"), folder, "def"))[0].rms_mm
    print("default scene RMS", rms)
    return rms


def test_the_chosen_exposures_keep_accuracy(dark_shiny: dict[str, object], default_rms: float) -> None:
    # issue 25: RMS <= 1.3x the default scene's. Measured with a 6 s budget: (10000, 40000, 160000) us, RMS 0.081
    # mm against the default scene's 0.070 mm (1.16x); period 16 alone 0.122 against 0.108 mm. What was left, the
    # dark pixels two from a bright patch (0.36 mm), went with the albedo-edge correction's slope limit (before it
    # 0.103 mm, 1.47x). The choice that covered most instead, (3536, 20000, 113137) us at 4 s, gave 0.162 mm with
    # period 16 alone
    s = dark_shiny["stats"]
    assert s.rms_mm <= 1.3 * default_rms, (s.line(), default_rms)  # type: ignore[attr-defined]


def test_the_most_precise_of_the_choices_that_cover() -> None:
    # the same scene's probe, every budget from 4 to 8 s: the choice covers >= 99 % of the lit pixels, within
    # COVERAGE_TOLERANCE of the most covering, and is the most precise of those by the noise model; rendered and
    # decoded, each is at least as accurate as the most covering choice of its budget (measured at 4 s: (7071,
    # 28284, 113137) us 0.149 mm against (3536, 20000, 113137) us 0.162 mm; at 5-8 s 0.137 against 0.158)
    import asyncio
    import tempfile

    from appliance.procedures import tune as t

    cfg = scene_config("dark_shiny")
    base = t.base_exposure_us(cfg)
    pr = asyncio.run(t.probe(cfg, tuple(base * f for f in t.PROBE_FACTORS)))
    seen: dict[tuple[int, ...], float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)

        def rms(exposures: tuple[int, ...]) -> float:
            if exposures not in seen:
                rig = capture(cfg, folder, "p", exposures)
                seen[exposures] = decode(folder, "p", rig)[0].rms_mm
            return seen[exposures]

        for budget in (4000, 5000, 8000):
            c = t.choose(pr, cfg.reconstruction.min_contrast_dn, 22, budget, base)
            assert c.within_budget and c.covered >= t.TARGET_SHARE and len(c.exposures_us) == 3, c
            coverage_first = _coverage_first(pr, cfg, budget, base)
            assert c.covered >= coverage_first.covered - t.COVERAGE_TOLERANCE, (c, coverage_first)
            print(budget, c.exposures_us, rms(c.exposures_us), coverage_first.exposures_us,
                  rms(coverage_first.exposures_us))
            assert rms(c.exposures_us) <= 0.95 * rms(coverage_first.exposures_us), (c, coverage_first)
            # the report names the most covering choice and how much noisier the model expects it
            assert tuple(e for e, _i in c.most_covering_passes) == coverage_first.exposures_us, c
            assert c.most_covering == coverage_first.covered and 0.5 < c.noise_ratio < 1.0, c
            assert any(line.startswith("the most precise of the choices") for line in c.lines(budget)), c.lines(budget)


def _coverage_first(pr: Probe, cfg: AppConfig, budget: float, base: float) -> TuneChoice:
    """The choice with no room for precision (coverage tolerance 0: the most covering, then the quickest)."""
    from appliance.procedures import tune as t

    return t.choose(pr, cfg.reconstruction.min_contrast_dn, 22, budget, base, coverage_tolerance=0.0)


def test_without_the_albedo_edge_correction_pixels_beside_clipped_ones_are_left_out(
    dark_shiny: dict[str, object], tmp_path: Path
) -> None:
    # edge_blur_px: 0 in a config file: the fusion's clean-neighbour rule again, reason "next to a clipped pixel"
    folder = dark_shiny["stats_folder"]
    assert isinstance(folder, Path)
    cfg = tmp_path / "off.yaml"
    cfg.write_text("reconstruction:\n  edge_blur_px: 0\n")
    off, out = decode(folder, "hdr", dark_shiny["rig"], config=cfg, tag="_off")  # type: ignore[arg-type]
    print(off.line())
    report = json.loads((folder / "hdr_off.json").read_text())
    on = dark_shiny["stats"]
    # measured 94.0 % complete, 0.626 % > 1 mm, 0.049 % beyond 5 sigma (corrected: 97.8 %, 0.082 %, 0.000 %)
    assert off.completeness < on.completeness - 0.02 and off.over_1mm > 3 * on.over_1mm, off.line()  # type: ignore[attr-defined]
    assert off.over_5sigma > 3 * on.over_5sigma, off.line()  # type: ignore[attr-defined]
    assert "next to a clipped pixel" in json.dumps(report), out
    # the sidecar says how many codes the correction moved (by more than 0.05 projector px), and none without it
    moved = json.loads((folder / "hdr.json").read_text())["counts"]["cameras"]["cam0"]["albedo_edge_corrected"]
    assert 1000 < moved < 0.2 * on.points, moved  # type: ignore[attr-defined]
    assert "albedo_edge_corrected" not in report["counts"]["cameras"]["cam0"]


def test_a_bad_time_budget_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "dark.yaml"
    path.write_text(scene_text("dark_shiny"))
    rc, text = _tune("--config", path, "--time-budget-ms", -5)
    assert rc == 2 and "Traceback" not in text
    assert "--time-budget-ms = -5.0: must be a positive number of ms" in text


def test_with_exposures_keeps_the_file_and_replaces_an_earlier_choice() -> None:
    text = "serial: X  # keep\nsequence:\n  kind: gray_phase   # comment\n  axes: x\nvirtual_rig: {}\n"
    once = with_exposures(text, (2500, 40000))
    assert once.startswith("serial: X  # keep\nsequence:\n  exposures_us: [2500, 40000]")
    assert "  kind: gray_phase   # comment\n" in once and once.endswith("virtual_rig: {}\n")
    twice = with_exposures(once, (10000,))
    assert twice.count("exposures_us") == 1 and "exposures_us: [10000]" in twice
    assert with_exposures("serial: X\n", (5,)) == "serial: X\nsequence:\n  exposures_us: [5]\n"
    flow = with_exposures("sequence: {kind: gray}\n", (7,))
    assert "exposures_us:\n  - 7" in flow or "exposures_us: [7]" in flow


def test_with_setting_keeps_the_file_and_replaces_an_earlier_value() -> None:
    text = "serial: X  # keep\nreconstruction:\n  mode: projector  # comment\nsequence:\n  axes: x\n"
    once = with_setting(text, "reconstruction", "edge_blur_px", 1.25)
    assert "reconstruction:\n  edge_blur_px: 1.25  # chosen by scan3d tune\n  mode: projector  # comment\n" in once
    assert once.startswith("serial: X  # keep\n") and once.endswith("sequence:\n  axes: x\n")
    twice = with_setting(once, "reconstruction", "edge_blur_px", 2)
    assert twice.count("edge_blur_px") == 1 and "edge_blur_px: 2  #" in twice
    added = with_setting("serial: X", "reconstruction", "edge_blur_px", 0.5)
    assert added == "serial: X\nreconstruction:\n  edge_blur_px: 0.5  # chosen by scan3d tune\n"
    flow = yaml.safe_load(with_setting("reconstruction: {mode: stereo}\n", "reconstruction", "edge_blur_px", 0.7))
    assert flow == {"reconstruction": {"mode": "stereo", "edge_blur_px": 0.7}}


def test_tune_measures_the_optics_blur_and_its_choice_keeps_sigma_honest(tmp_path: Path) -> None:
    # the default scene with the camera's and the projector's blur at 1.5 px (the rig's defaults: 0.5 and 0.6):
    # with the configured edge_blur_px (0.5) one exposure puts 0.141 % of the points beyond 5 sigma
    # (test_hard_scenes' xfail). tune's probe measures the blur from fringes at two periods and --apply writes
    # the cameras' for the albedo-edge correction: measured 1.49 (projector 1.51). It chooses 10 and 40 ms (the
    # blur lowers the contrast); the 40 ms pass clips half the scene, and the blur carries that light 3-4 px: at
    # 0.5 px those passes gave 0.344 % beyond 5 sigma, |err|/sigma RMS 5.1, RMS 0.82 mm. With the written 1.49 px
    # the fusion's clean rule reaches 5 px (decode_plan.CLEAN_SIGMAS): 0.050 %, 0.89, RMS 0.44 mm, 96.9 % complete
    path = tmp_path / "tuned.yaml"
    text = scene_text("default").replace("seed: 3,", "seed: 3, camera_blur_px: 1.5, projector_blur_px: 1.5,")
    path.write_text(text)
    rc, out = _tune("--config", path, "--time-budget-ms", 4000, "--apply")
    print(out)
    assert rc == 0, out
    assert re.search(r"optics: cam0: camera blur sigma 1\.[45]\d camera px, projector blur sigma 1\.[45]\d", out), out
    assert "choice: reconstruction.edge_blur_px = " in out and "(now 0.5)" in out
    cfg = load_config(path)
    assert abs(cfg.reconstruction.edge_blur_px - 1.5) <= 0.08, cfg.reconstruction.edge_blur_px
    assert "reconstruction.edge_blur_px = " in out.split("written: ")[1]
    from appliance.config import parse_config

    rig = capture(parse_config(text, "blur.yaml"), tmp_path, "blur", cfg.sequence.exposures_us)
    s, _ = decode(tmp_path, "blur", rig, path)
    print(s.line())
    assert s.over_5sigma <= 1e-3 and 0.7 <= s.z_rms <= 1.4, s.line()
    assert s.completeness >= 0.96, s.line()


def test_with_exposures_takes_out_intensities_left_from_an_earlier_configuration() -> None:
    # tune's passes are at full intensity; an intensities list for other passes would make the file invalid
    text = ("sequence:\n  kind: gray_phase\n  exposures_us: [10000, 10000, 40000]\n  intensities:\n    - 0.25\n"
            "    - 1\n    - 1\n  axes: x  # keep\n")  # fmt: skip
    out = with_exposures(text, (2500, 40000))
    assert "intensities" not in out and "exposures_us: [2500, 40000]" in out and "  axes: x  # keep\n" in out
    assert "intensities" not in with_exposures("sequence: {exposures_us: [1, 2], intensities: [0.5, 1]}\n", (7,))
    both = with_exposures(text, (10000, 10000), (0.25, 1.0))
    assert "intensities: [0.25, 1]" in both and both.count("intensities") == 1


def test_apply_replaces_a_dimmed_pass_configuration(tmp_path: Path) -> None:
    # a file that scanned with a dimmed pass (sequence.intensities): tune --apply writes its choice and the file
    # stays valid
    path = tmp_path / "dimmed.yaml"
    text = scene_text("dark_shiny").replace("  periods_px: [16, 8]\n", "  periods_px: [16, 8]\n  exposures_us: [10000, "
                                                                      "10000]\n  intensities: [0.25, 1]\n")
    assert "intensities" in text
    path.write_text(text)
    assert load_config(path).sequence.intensities == (0.25, 1.0)
    rc, out = _tune("--config", path, "--time-budget-ms", 4000, "--apply")
    assert rc == 0 and "Traceback" not in out, out
    cfg = load_config(path)
    assert cfg.sequence.intensities == () and list(cfg.sequence.exposures_us) == _choice(out)


def test_what_clips_at_the_shortest_exposure_gets_a_dimmed_pass(tmp_path: Path) -> None:
    # the dark-and-shiny scene configured at 80 ms (an over-exposed scan): the ladder's shortest exposure is
    # 20 ms, where the white patches and the sphere's highlight (8x the white level) still clip, more than the
    # 1 % the target leaves. The sim projector can dim, so the probe measures them with the projector at 1/16 and
    # the choice takes a pass dimmed; the file gets sequence.intensities, and the rendered passes reconstruct them
    # (at 40 ms only the highlight's 0.4 % clips at the shortest exposure: the choice then weighs its coverage
    # against the precision of the rest, test_the_most_precise_of_the_choices_that_cover)
    path = tmp_path / "over.yaml"
    path.write_text(scene_text("dark_shiny", exposure_us=80_000))
    rc, text = _tune("--config", path, "--time-budget-ms", 4000, "--apply")
    print(text)
    assert rc == 0, text
    cfg = load_config(path)
    exposures, levels = cfg.sequence.exposures_us, cfg.sequence.intensities
    assert len(exposures) <= 3 and len(levels) == len(exposures) and min(levels) < 1.0, (exposures, levels)
    assert "with the projector dimmed" in text and "sequence.intensities = " in text
    assert "clipped even at" not in text
    rig = capture(scene_config("dark_shiny", exposure_us=80_000), tmp_path, "dim", exposures, levels)
    dimmed, _ = decode(tmp_path, "dim", rig)
    # the same exposures with the projector at full intensity in every pass
    capture(scene_config("dark_shiny", exposure_us=80_000), tmp_path, "full", exposures)
    full, _ = decode(tmp_path, "full", rig)
    print("dimmed:", dimmed.line())
    print("full:  ", full.line())
    # the patch edges' 0.1 % > 1 mm, as with the 3 exposures chosen at 10 ms (their sigma says so)
    assert dimmed.completeness >= 0.97 and dimmed.over_1mm <= 2e-3, dimmed.line()
    assert dimmed.over_5sigma <= 1e-3 and dimmed.completeness > full.completeness, (dimmed.line(), full.line())
    # the highlight's pixels: clipped in the shortest pass at full intensity
    from appliance.patterns.sequence import WhiteFrame
    white = rig.render_frame(WhiteFrame(), "cam0", exposure_us=min(exposures))
    dim_white = rig.render_frame(WhiteFrame(), "cam0", exposure_us=min(exposures), intensity=min(levels))
    hot = (white >= 255) & rig.ground_truth("cam0").lit
    kept = hot & (dim_white < 0.95 * 255)  # ... and not clipped in the dimmed pass
    got = {t: np.zeros(hot.shape, bool) for t in ("dim", "full")}
    for t in got:
        v = read_ply_vertices(tmp_path / f"{t}.ply")
        got[t][np.asarray(v["row"]), np.asarray(v["col"])] = True
    print(f"highlight: {hot.sum()} px, reconstructed {got['dim'][hot].mean():.3f} dimmed, "
          f"{got['full'][hot].mean():.3f} at full intensity; of the {kept.sum()} the dimmed pass did not clip "
          f"{got['dim'][kept].mean():.3f}")
    assert hot.sum() > 300 and kept.sum() > 0.3 * hot.sum()
    # (at full intensity some of them still decode: their white frame clips, their pattern frames not all)
    # measured: 24524 px, 96.9 % reconstructed dimmed, 22.1 % at full intensity; 98.8 % of the 24047 not clipped
    assert got["dim"][kept].mean() >= 0.9 and got["dim"][hot].mean() >= got["full"][hot].mean() + 0.5


def test_a_projector_that_cannot_dim_gets_exposures_only() -> None:
    # choose() on a probe without a dimmed pass (an HDMI projector): a pixel that clips at every probe exposure
    # is named as clipped, with what to do, and the choice has no intensities
    from appliance.procedures.tune import Probe, choose

    e = (2500.0, 10_000.0, 40_000.0)
    rate = np.full((1, 100), 10.0 / 1000)  # DN per µs: 25, 100, 400 (clipped at 40 ms)
    rate[0, :5] = 1.0  # 2500 DN at the shortest: clipped everywhere
    white = np.minimum(np.stack([rate * t + 5 for t in e]), 255.0)
    black = np.full_like(white, 5.0)
    c = choose(Probe(e, {"c": white}, {"c": black}, {"c": 255.0}), 4.0, 22, 10_000, 10_000)
    assert c.intensities == () and c.dim_floor == 1.0 and abs(c.clipped - 0.05) < 1e-9
    assert any("projector that can dim" in line for line in c.lines(10_000)), c.lines(10_000)
    # the same scene with a dimmed probe pass at 1/16: the clipped pixels get a dimmed pass
    e2 = (2500.0, *e)
    white2 = np.concatenate([np.minimum(rate[None] * 2500 / 16 + 5, 255.0), white])
    c2 = choose(Probe(e2, {"c": white2}, {"c": np.full_like(white2, 5.0)}, {"c": 255.0},
                      intensities=(1 / 16, 1.0, 1.0, 1.0)), 4.0, 22, 10_000, 10_000)
    assert c2.clipped == 0.0 and c2.covered == 1.0 and c2.intensities and min(c2.intensities) < 0.25, c2
