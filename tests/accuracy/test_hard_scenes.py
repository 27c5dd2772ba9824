"""Issue 25's hard scenes on the virtual rig, with exact truth: over-exposure, a bright hall, a diffuse groove
(one-bounce interreflection) and a mirror groove. Each is rendered (camera 480x384, the default sequence:
periods [16, 8]; where a test says so, period 16 alone, the default before),
reconstructed by ``scan3d decode`` and compared point by point with the truth: completeness of the lit
pixels, share of points > 1 mm off, and the calibration of the per-point sigma (|error| / sigma RMS in
0.7-1.4, <= 0.1 % beyond 5 sigma).

Targets the decoder does not reach yet are strict xfails that state the numbers measured when they were written.
The multi-exposure dark-and-shiny scene is in ``tests/commands/test_tune.py`` (with the exposures scan3d tune
chooses).
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest
from hard_scenes import SceneStats, capture, decode, measure, scene_config, scene_text

from appliance import cli
from appliance.config import load_config
from appliance.output.ply import read_ply_vertices
from appliance.sim.rig import VirtualRig

SIGMA_RMS = (0.7, 1.4)


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("hard")


def _sigma_is_honest(s: SceneStats) -> None:
    assert SIGMA_RMS[0] <= s.z_rms <= SIGMA_RMS[1], s.line()
    assert s.over_5sigma <= 1e-3, s.line()


def test_default_scene_small_render(folder: Path) -> None:
    rig = capture(scene_config("default"), folder, "default")
    s, said = decode(folder, "default", rig)
    print(s.line())
    assert "came another way" not in said, said  # no interreflection here: no widened sigma to speak of
    assert s.completeness >= 0.97 and s.over_1mm <= 1e-4 and s.rms_mm <= 0.15, s.line()
    _sigma_is_honest(s)


def test_over_exposed_4x_single_exposure_puts_out_no_wrong_point(folder: Path) -> None:
    # the dark-and-shiny plane at 4x: its bright patches and the sphere's highlight clip at 255
    s = measure(scene_config("dark_shiny", exposure_us=40_000), folder, "over")
    print(s.line())
    assert s.over_1mm <= 1e-3, s.line()
    _sigma_is_honest(s)


def test_bright_hall_holds(folder: Path) -> None:
    # ambient light at 80 % of the projector's white level (white 120 DN at albedo 1, so nothing clips)
    s = measure(scene_config("default", ambient_dn=96, gain_dn=120), folder, "hall")
    print(s.line())
    assert s.completeness >= 0.97 and s.over_1mm <= 1e-3, s.line()
    _sigma_is_honest(s)


def test_matte_groove_without_interreflection(folder: Path) -> None:
    # the concave corner's geometry alone (interreflection off)
    s = measure(scene_config("diffuse_groove"), folder, "dgroove0")
    print(s.line())
    assert s.completeness >= 0.97 and s.over_1mm <= 1e-3, s.line()
    _sigma_is_honest(s)


def _blurred_default(folder: Path) -> VirtualRig:
    """The default scene with the camera's and the projector's blur at 1.5 px (the virtual rig's defaults: 0.5 and
    0.6 px), captured once for the module; its rig (the truth)."""
    from appliance.config import parse_config

    text = scene_text("default").replace("seed: 3,", "seed: 3, camera_blur_px: 1.5, projector_blur_px: 1.5,")
    cfg = parse_config(text, "blur.yaml")
    if (folder / "blur15.yaml").exists():
        return VirtualRig(cfg.virtual_rig)
    return capture(cfg, folder, "blur15")


@pytest.mark.xfail(strict=True, reason="not reached yet: at 1.5 px blur with the default edge_blur_px (0.5 px) "
                   "measured 0.141 % beyond 5 sigma, |err|/sigma RMS 1.07, 0.251 % of the points > 1 mm, RMS 0.423 "
                   "mm, 96.7 % complete (period 16 alone: 0.223 %, 1.41, 0.369 %, 0.56 mm): the albedo-edge correction "
                   "and its sigma assume the blur they are given; scan3d tune measures it and --apply writes it "
                   "(test_tune.py::test_tune_measures_the_optics_blur_and_its_choice_keeps_sigma_honest), the scan "
                   "does not measure it itself")
def test_default_scene_with_stronger_blur_keeps_sigma_honest(folder: Path) -> None:
    s, _ = decode(folder, "blur15", _blurred_default(folder))
    print(s.line())
    _sigma_is_honest(s)


def test_stronger_blur_with_edge_blur_px_set_to_it_keeps_sigma_honest(folder: Path) -> None:
    # reconstruction.edge_blur_px: 1.5 in a config file, the optics' true blur: measured 0.027 % beyond 5 sigma,
    # |err|/sigma RMS 0.85 (the points > 1 mm, 0.158 %, have a sigma that says so; period 16 alone: 0.032 %, 1.04)
    rig = _blurred_default(folder)
    (folder / "edge15.yaml").write_text("reconstruction:\n  edge_blur_px: 1.5\n")
    s, _ = decode(folder, "blur15", rig, folder / "edge15.yaml", "_edge15")
    print(s.line())
    _sigma_is_honest(s)


@pytest.mark.parametrize("samples", [8, 64])
def test_diffuse_groove_sigma_says_how_far_interreflection_shifts_a_point(folder: Path, samples: int) -> None:
    # a matte concave corner (albedo 0.9) whose faces light each other (one bounce, `samples` hemisphere samples a
    # pixel). Near the corner the indirect light comes from the nearby face, whose codes are close to the pixel's
    # and do not average out: it shifts the phase. The pixel's fringe share (its phase modulation over its white -
    # black range) falls there, and its sigma widens (reconstruction.indirect_sigma; without it 0.30 % (8
    # samples) and 0.155 % (64) of the points lie beyond 5 sigma, |err|/sigma RMS 1.22 and 0.98)
    s = measure(scene_config("diffuse_groove", bounce=samples), folder, f"dgroove{samples}")
    print(s.line())
    assert s.completeness >= 0.96, s.line()  # measured 96.7 % (8 samples), 97.7 % (64)
    _sigma_is_honest(s)  # measured 0.053 % and 0.023 % beyond 5 sigma, |err|/sigma RMS 0.99 and 0.85


def test_indirect_sigma_off_in_the_config_file_leaves_sigma_to_the_noise(folder: Path) -> None:
    # the same capture decoded with reconstruction.indirect_sigma: false: the same points, narrower sigma
    rig = capture(scene_config("diffuse_groove", bounce=64), folder, "dgroove_knob")
    on, said_on = decode(folder, "dgroove_knob", rig)
    (folder / "no_indirect.yaml").write_text("reconstruction:\n  indirect_sigma: false\n")
    off, said_off = decode(folder, "dgroove_knob", rig, folder / "no_indirect.yaml", "_off")
    # a quarter of the points lie where the faces light each other: said in plain words, with what to do
    line = "of camera cam0's points are lit partly by light that came another way"
    assert line in said_on and "reconstruction.max_sigma_mm" in said_on and line not in said_off, said_on
    print("on: ", on.line())
    print("off:", off.line())
    assert on.points == off.points and on.rms_mm == off.rms_mm
    assert off.over_5sigma >= 4 * on.over_5sigma and off.over_5sigma > 1e-3  # measured 0.155 % against 0.023 %
    a, b = (read_ply_vertices(folder / f"dgroove_knob{t}.ply") for t in ("", "_off"))
    sa, sb = np.asarray(a["sigma_mm"]), np.asarray(b["sigma_mm"])
    assert np.all(sa >= sb) and np.mean(sa > sb) < 0.25  # widened only, and only where the fringe share fell


def test_diffuse_groove_holds(folder: Path) -> None:
    # one-bounce diffuse interreflection of 64 samples a pixel: near the corner the nearby face's light does not
    # average out and shifts the phase; period 8 shifts half as many projector px and averages out more. Measured
    # 0.010 % of the points > 1 mm, RMS 0.117 mm, 97.7 % complete, 0 beyond 5 sigma; period 16 alone 0.203 %,
    # 0.191 mm (99.4 % of those points within 5 mm of the corner line). Without interreflection 0 %
    s = measure(scene_config("diffuse_groove", bounce=64), folder, "dgroove")
    one = _period_16_alone(folder, "diffuse_groove", "dgroove_16", bounce=64)
    print("[16, 8]:", s.line())
    print("[16]:   ", one.line())
    assert s.completeness >= 0.97 and s.over_1mm <= 1e-3, s.line()
    assert s.over_1mm <= 0.25 * one.over_1mm, (s.line(), one.line())
    _sigma_is_honest(s)


def _period_16_alone(folder: Path, scene: str, name: str, **kwargs: object) -> SceneStats:
    """A scene captured and decoded with period 16 alone (the default sequence before periods [16, 8])."""
    from appliance.config import parse_config

    return measure(parse_config(scene_text(scene, periods="[16]", **kwargs), f"{name}.yaml"), folder, name)  # type: ignore[arg-type]


def test_the_second_period_against_period_16_alone_on_blurred_optics(folder: Path) -> None:
    # at 1.5 px camera and projector blur period 8 keeps ~14 % of period 16's modulation: each pixel stays on the
    # coarser set where that is the more precise (the finer's modulation under half the coarser's, the period
    # ratio), with the coarser period's sigma. Measured (edge_blur_px 1.5): RMS 0.423 mm against 0.542 mm with
    # period 16 alone on the same blur, 96.7 % complete against 96.9 %. Before, a period ratio of 2 had no fallback
    # (0.3 % complete), every pixel whose finer modulation cleared the floor took the blurred set, and a pixel left
    # on the coarser set had the finer period's sigma (0.68 % beyond 5 sigma)
    from appliance.config import parse_config

    blur = "seed: 3, camera_blur_px: 1.5, projector_blur_px: 1.5,"
    text = scene_text("default", periods="[16]").replace("seed: 3,", blur)
    rig = capture(parse_config(text, "blur16.yaml"), folder, "blur15_16")
    (folder / "edge15.yaml").write_text("reconstruction:\n  edge_blur_px: 1.5\n")
    one, _ = decode(folder, "blur15_16", rig, folder / "edge15.yaml", "_edge15")
    two, _ = decode(folder, "blur15", _blurred_default(folder), folder / "edge15.yaml", "_edge15")
    print("[16, 8]:", two.line())
    print("[16]:   ", one.line())
    assert two.completeness >= one.completeness - 0.005 and two.rms_mm < one.rms_mm, (two.line(), one.line())
    _sigma_is_honest(two)


def test_the_second_period_against_period_16_alone_on_the_default_scene(folder: Path) -> None:
    # sharp optics (the virtual rig's 0.5 / 0.6 px): measured RMS 0.070 mm against 0.108 mm with period 16 alone,
    # 97.6 % complete either way, sigma honest
    two = measure(scene_config("default"), folder, "default_two")
    one = _period_16_alone(folder, "default", "default_16")
    print("[16, 8]:", two.line())
    print("[16]:   ", one.line())
    assert two.rms_mm <= 0.75 * one.rms_mm and two.completeness >= one.completeness - 0.002, (two.line(), one.line())
    _sigma_is_honest(two)


@pytest.fixture(scope="module")
def mirror_groove(folder: Path) -> SceneStats:
    """The mirror groove at the scene's 10 ms with the default sequence."""
    s = measure(scene_config("mirror_groove"), folder, "mgroove")
    print(s.line())
    return s


def test_mirror_groove_has_no_ghost_points(folder: Path, mirror_groove: SceneStats) -> None:
    # a concave corner whose left face is a mirror (reflectance 0.6): the right face gets a second copy of the
    # pattern from the mirrored projector, and the camera sees the lit right face in the mirror. Measured at the
    # scene's 10 ms, the two copies taken apart on the right face (reconstruction.separate_copies): 0.012 % of the
    # points > 1 mm, none > 5 mm, none beyond 5 sigma, |err|/sigma RMS 0.87, RMS 0.134 mm, 85.8 % complete (without
    # the separation 0.014 %, 0.91, 0.137 mm, 70.8 %). Period 16 alone (one phase set: nothing to take apart):
    # 0.150 % > 1 mm (0.19 k points on the mirror face 1-5 mm off, scattered over its outer strip: the noise of its
    # dim diffuse light, albedo 0.15, that period 8 halves), RMS 0.21 mm. Period 16 alone without the check for
    # regions walled in by reflections 2.0 %, 0.17 % > 5 mm; without it and the projector visibility check 3.6 %,
    # 1.8 %; without all three and the check for two copies of the pattern 17.2 %, 6.7 %
    one = _period_16_alone(folder, "mirror_groove", "mgroove_16")
    print("[16]:", one.line())
    s = mirror_groove
    assert s.over_1mm <= 1e-3 and s.over_5mm == 0.0, s.line()
    assert s.over_1mm <= 0.25 * one.over_1mm, (s.line(), one.line())
    _sigma_is_honest(s)


def test_mirror_groove_is_complete(mirror_groove: SceneStats) -> None:
    # issue 25's target, 85 %: measured 85.8 % (69.8 % before the two copies were taken apart, 84.8 % before the
    # image's border kept its points). What is left: a 5 px band along the corner line on the matte face, where the
    # copies nearly coincide and the planes would extrapolate; on the mirror face the pixels that see the lit face
    # in the mirror (the reflection is the stronger copy: not taken apart)
    assert mirror_groove.completeness >= 0.85, mirror_groove.line()


@pytest.fixture(scope="module")
def tuned_mirror_groove(folder: Path) -> SceneStats:
    """The mirror groove scanned with what ``scan3d tune --apply`` writes into its configuration file."""
    path = folder / "mirror.yaml"
    path.write_text(scene_text("mirror_groove"))
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = cli.main(["tune", "--config", str(path), "--time-budget-ms", "4000", "--apply"])
    print(out.getvalue())
    assert rc == 0, out.getvalue()
    exposures = load_config(path).sequence.exposures_us
    s = decode(folder, "mgroove_tuned", capture(scene_config("mirror_groove"), folder, "mgroove_tuned", exposures))[0]
    print(exposures, s.line())
    return s


def test_mirror_groove_with_what_tune_chooses_has_no_wrong_points(tuned_mirror_groove: SceneStats) -> None:
    # tune takes one exposure, 14 ms (the mirror face's dim diffuse light gains SNR): measured none of the points
    # > 1 mm, none beyond 5 sigma, |err|/sigma RMS 0.87, RMS 0.10 mm, 85.9 % complete (before the two copies were
    # taken apart: 0.013 %, 0.88, 0.16 mm, 69.9 %)
    s = tuned_mirror_groove
    assert s.over_1mm <= 1e-3 and s.over_5mm <= 1e-4, s.line()
    _sigma_is_honest(s)


def test_mirror_groove_with_what_tune_chooses_is_complete(tuned_mirror_groove: SceneStats) -> None:
    # measured 85.9 % with tune's 14 ms (69.9 % before the two copies were taken apart)
    assert tuned_mirror_groove.completeness >= 0.85, tuned_mirror_groove.line()


def test_mirror_groove_in_two_exposures_keeps_the_reflection_checks(folder: Path) -> None:
    # an HDR capture (10 and 40 ms) fuses per pixel; the pixels lit by two copies of the pattern in each pass stay
    # evidence for the visibility check, offline as in the service's streaming fusion (before, the offline fusion
    # dropped them: no check ran, RMS 52 mm, 1.2 % of the points > 5 mm); each pass takes the two copies apart, and
    # the fused maps keep the separated pixels of the pass each pixel came from. Measured: none > 1 mm, none beyond
    # 5 sigma, RMS 0.12 mm, 85.8 % complete (before the separation: 0.002 % > 5 mm, RMS 0.27 mm, 70.1 %)
    from appliance.config import parse_config
    from appliance.patterns.from_config import build_sequence
    from appliance.patterns.sequence import Sequence
    from appliance.reconstruct.decode import DecodeParams
    from appliance.reconstruct.hdr import HdrStreamingDecoder, decode_passes

    exposures = (10_000, 40_000)
    rig = capture(scene_config("mirror_groove"), folder, "mgroove_hdr", exposures)
    s, _ = decode(folder, "mgroove_hdr", rig)
    print(s.line())
    assert s.over_1mm <= 1e-3 and s.over_5mm <= 1e-4, s.line()
    _sigma_is_honest(s)
    _, cam = _camera_block(folder, "mgroove_hdr")
    reasons = cam["reasons"]
    assert isinstance(reasons, dict) and reasons.get("hidden from the projector", 0) > 0, reasons
    # the offline fusion and the streaming one carry the same evidence
    stack = np.load(folder / "mgroove_hdr.npy")
    one = build_sequence(parse_config(scene_text("mirror_groove"), "m.yaml").sequence, rig.projector.width,
                         rig.projector.height)
    seq = Sequence(one.width, one.height, tuple(one.frames) * len(exposures))
    per_frame = [(float(e), 1.0) for e in exposures for _ in one.frames]
    offline, _c, _p = decode_passes(stack, seq, per_frame, DecodeParams())
    dec = HdrStreamingDecoder(seq, per_frame, stack.shape[1:], stack.dtype, DecodeParams())
    for i in range(len(seq)):
        dec.push(i, stack[i])
    streamed = dec.finish()
    assert offline.blend_codes is not None and streamed.blend_codes is not None
    assert len(offline.blend_codes) > 0.05 * stack[0].size
    np.testing.assert_array_equal(offline.blend_codes, streamed.blend_codes)
    assert offline.separated is not None and streamed.separated is not None and len(offline.separated) > 1000
    np.testing.assert_array_equal(offline.separated, streamed.separated)
    np.testing.assert_array_equal(offline.u, streamed.u)


def test_mirror_groove_pixels_lit_by_two_patterns_are_dropped_and_said(folder: Path) -> None:
    # the same capture decoded with the check for two copies of the pattern (reconstruction.blend_ratio, on by
    # default) and without it: the matte face adds the direct and the mirrored pattern, so several of its fine Gray
    # bits have the contrast of a difference of two lights
    rig = capture(scene_config("mirror_groove"), folder, "mgroove_blend")
    on, _ = decode(folder, "mgroove_blend", rig)
    (folder / "no_blend_check.yaml").write_text("reconstruction: {blend_ratio: 0}\n")
    off, _ = decode(folder, "mgroove_blend", rig, folder / "no_blend_check.yaml", "_off")
    print("check on: ", on.line())
    print("check off:", off.line())
    assert on.over_1mm <= 0.3 * off.over_1mm, (on.line(), off.line())  # measured 17.2 % -> 3.6 %
    assert on.over_5mm <= 0.4 * off.over_5mm, (on.line(), off.line())  # 6.7 % -> 1.8 %
    cams = {t: json.loads((folder / f"mgroove_blend{t}.json").read_text())["counts"]["cameras"]["cam0"]
            for t in ("", "_off")}  # fmt: skip
    # the check's pixels: those whose direct copy came apart decode (counted as "separated"), the rest are said
    said = cams[""]["reasons"].get("two copies of the pattern", 0)
    apart = cams[""].get("separated", 0)
    assert said >= 0.03 * cams[""]["pixels"] and apart >= 0.1 * cams[""]["pixels"], cams[""]
    assert "two copies of the pattern" not in cams["_off"]["reasons"] and "separated" not in cams["_off"]


# --- the projector visibility check: a point the projector cannot light is a ghost ----------------------------


def _errors(folder: Path, name: str, rig: VirtualRig) -> dict[tuple[int, int], float]:
    """Per pixel (row, col) of a decoded cloud its distance to the truth (mm)."""
    v = read_ply_vertices(folder / f"{name}.ply")
    r, c = np.asarray(v["row"], int), np.asarray(v["col"], int)
    xyz = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    err = np.linalg.norm(xyz - rig.ground_truth("cam0").xyz[r, c], axis=1)
    return {(int(a), int(b)): float(e) for a, b, e in zip(r, c, err, strict=True)}


@pytest.mark.parametrize("axes", ["x", "xy"])
def test_mirror_groove_points_hidden_from_the_projector_are_dropped_and_said(folder: Path, axes: str) -> None:
    # (period 16 alone: the checks' A/B on the sequence that gives them the most to drop)
    # the camera sees the lit matte face in the mirror: those pixels decode the matte face's codes and triangulate
    # behind it, where the projector's rays have already met the matte face (or its pixels lit by two copies of
    # the pattern, evidence only); hidden_check auto runs because 20 % of the decoded pixels show two copies
    name = f"mgroove_hidden_{axes}"
    rig = capture(scene_config("mirror_groove", axes=axes, periods="[16]"), folder, name)
    on, _ = decode(folder, name, rig)
    (folder / "no_hidden_check.yaml").write_text("reconstruction: {hidden_check: 'off'}\n")
    off, _ = decode(folder, name, rig, folder / "no_hidden_check.yaml", "_off")
    print("check on: ", on.line())
    print("check off:", off.line())
    # measured x: 53.5 -> 0.48 mm RMS, > 5 mm 1.81 -> 0.17 %; xy: 16.1 -> 0.48 mm, 1.19 -> 0.17 %
    assert off.rms_mm >= 10.0 and on.rms_mm <= 1.0, (on.line(), off.line())
    assert on.over_5mm <= 0.25 * off.over_5mm, (on.line(), off.line())
    e_on, e_off = _errors(folder, name, rig), _errors(folder, f"{name}_off", rig)
    dropped = [e for p, e in e_off.items() if p not in e_on]
    assert set(e_on) <= set(e_off)
    print(f"dropped {len(dropped)}: {np.mean(np.asarray(dropped) > 1.0):.1%} of them > 1 mm off")
    # the hidden points (98.4 % of them > 1 mm off) and the band walled in by reflections next to the corner
    # line (73 %: its points nearest the line are within 1 mm): measured 83.2 % (x), 80.4 % (xy)
    assert len(dropped) >= 0.01 * len(e_on) and np.mean(np.asarray(dropped) > 1.0) >= 0.75
    report, cam = _camera_block(folder, name)
    reasons = cam["reasons"]
    _, cam_off = _camera_block(folder, f"{name}_off")
    reasons_off = cam_off["reasons"]
    assert isinstance(reasons, dict) and isinstance(reasons_off, dict)
    walled = reasons["two copies of the pattern"] - reasons_off["two copies of the pattern"]
    # points left without neighbours are dropped in both runs, but not the same ones (measured x: 24 fewer with
    # the check, whose drops took them first)
    alone = reasons.get("filtered", 0) - reasons_off.get("filtered", 0)
    assert abs(alone) <= 0.01 * len(dropped), (reasons, reasons_off)
    assert walled > 0 and reasons["hidden from the projector"] + walled + alone == len(dropped), (reasons, reasons_off)
    assert reasons["decoded"] == cam["points"] and sum(reasons.values()) == cam["pixels"]
    assert "hidden from the projector" not in reasons_off
    health = report["calibration_health"]
    assert isinstance(health, dict) and health["status"] in ("ok", "not measured"), health


@pytest.mark.parametrize("axes", ["x", "xy"])
def test_mirror_groove_band_walled_in_by_reflections_is_dropped(
    folder: Path, axes: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # next to the corner line the mirrored copy of the pattern nearly coincides with the direct one: a band of
    # blended codes on the matte face (1-2 mm off) and ghosts on the mirror's side (5-50 mm), that no pixel-local
    # check sees; farther out both sides were dropped (two copies; hidden), so the band is walled in by them
    # (period 16 alone: the check's A/B on the sequence that gives it the most to drop)
    from appliance.reconstruct import walled

    name = f"mgroove_walled_{axes}"
    rig = capture(scene_config("mirror_groove", axes=axes, periods="[16]"), folder, name)
    on, _ = decode(folder, name, rig)
    monkeypatch.setattr(walled, "WALL_SHARE", 2.0)  # never: the check off, everything else as it is
    off, _ = decode(folder, name, rig, tag="_off")
    print("check on: ", on.line())
    print("check off:", off.line())
    # measured x: > 1 mm 2.03 -> 0.155 %, > 5 mm 0.169 -> 0 %, beyond 5 sigma 0.31 -> 0 %, |err|/sigma RMS
    # 1.09 -> 0.87, 71.7 -> 69.9 % complete; xy: 1.91 -> 0.157 %, 0.170 -> 0 %, 0.27 -> 0 %, 1.01 -> 0.78
    assert on.over_1mm <= 0.1 * off.over_1mm and on.over_5mm <= 0.05 * off.over_5mm, (on.line(), off.line())
    assert on.completeness >= off.completeness - 0.025, (on.line(), off.line())
    _sigma_is_honest(on)
    e_on, e_off = _errors(folder, name, rig), _errors(folder, f"{name}_off", rig)
    assert set(e_on) <= set(e_off)
    gone = [p for p in e_off if p not in e_on]
    # one band along the corner line (the image column where the faces meet): every dropped pixel within 16 px
    gt = rig.ground_truth("cam0")
    corner = np.flatnonzero(np.any(gt.object_id[:, 1:] != gt.object_id[:, :-1], axis=0)
                            & np.any((gt.object_id[:, 1:] == 1) & (gt.object_id[:, :-1] == 0), axis=0))  # fmt: skip
    assert corner.size, "the corner line's column"
    cols = np.asarray([c for _r, c in gone])
    assert np.all(np.abs(cols - np.median(corner)) <= 16), (np.median(corner), cols.min(), cols.max())
    _, cam = _camera_block(folder, name)
    _, cam_off = _camera_block(folder, f"{name}_off")
    said, said_off = cam["reasons"], cam_off["reasons"]
    assert isinstance(said, dict) and isinstance(said_off, dict)
    alone = said.get("filtered", 0) - said_off.get("filtered", 0)  # points left without neighbours, in both runs
    assert abs(alone) <= 0.01 * len(gone), (said, said_off)
    walled = said["two copies of the pattern"] - said_off["two copies of the pattern"]
    assert walled + alone == len(gone), (said, said_off)


def test_a_scene_with_projector_shadows_and_no_mirror_loses_nothing_to_the_visibility_check(folder: Path) -> None:
    # the default scene (a box and a sphere before a plane: the projector's shadows, steep faces): auto does not
    # run the check (no reflection shown), and always drops nothing
    rig = capture(scene_config("default"), folder, "default_hidden")
    auto, _ = decode(folder, "default_hidden", rig)
    (folder / "always.yaml").write_text("reconstruction: {hidden_check: always}\n")
    always, _ = decode(folder, "default_hidden", rig, folder / "always.yaml", "_always")
    assert always.line() == auto.line(), (auto.line(), always.line())
    for tag in ("", "_always"):
        _, cam = _camera_block(folder, f"default_hidden{tag}")
        assert isinstance(cam["reasons"], dict) and "hidden from the projector" not in cam["reasons"]
    assert set(_errors(folder, "default_hidden", rig)) == set(_errors(folder, "default_hidden_always", rig))


# --- both projector axes: each pixel's (u, v) must lie on its epipolar line -------------------------------


def _camera_block(folder: Path, name: str) -> tuple[dict[str, object], dict[str, object]]:
    report = json.loads((folder / f"{name}.json").read_text())
    return report, report["counts"]["cameras"]["cam0"]


def test_default_scene_coded_on_both_axes_loses_nothing_to_the_epipolar_check(folder: Path) -> None:
    s = measure(scene_config("default", axes="xy"), folder, "default_xy")
    print(s.line())
    report, cam = _camera_block(folder, "default_xy")
    assert s.completeness >= 0.97 and s.over_1mm <= 1e-4, s.line()
    _sigma_is_honest(s)
    reasons = cam["reasons"]
    assert isinstance(reasons, dict)
    # a handful at most: pixels on a shadow's edge whose code the albedo-edge correction moves with a slope from
    # one side (measured 3 of 173 k; none without the correction)
    assert reasons.get("off the epipolar line", 0) <= 1e-4 * reasons["decoded"], reasons
    assert reasons["decoded"] == cam["points"] and sum(reasons.values()) == cam["pixels"]
    assert report["warnings"] == []


def test_mirror_groove_on_both_axes_drops_ghosts_off_the_epipolar_line_and_says_why(folder: Path) -> None:
    # one axis: every code meets every camera ray, nothing to check; both: a ghost's (u, v) comes from the
    # mirrored projector and mostly misses the pixel's epipolar line in the real one
    # (the check for two copies of the pattern off, to see this check alone)
    off = folder / "no_blend_check_epi.yaml"
    off.write_text("reconstruction: {blend_ratio: 0}\n")
    one = decode(folder, "mgroove_x", capture(scene_config("mirror_groove"), folder, "mgroove_x"), off)[0]
    both = decode(folder, "mgroove_xy", capture(scene_config("mirror_groove", axes="xy"), folder, "mgroove_xy"),
                  off)[0]  # fmt: skip
    print("x: ", one.line())
    print("xy:", both.line())
    assert both.over_5mm <= 0.5 * one.over_5mm, (one.line(), both.line())  # measured 6.7 % -> 2.4 %
    report, cam = _camera_block(folder, "mgroove_xy")
    reasons = cam["reasons"]
    assert isinstance(reasons, dict) and isinstance(cam["pixels"], int)
    assert reasons["off the epipolar line"] > 0.02 * cam["pixels"], reasons
    assert reasons["decoded"] == cam["points"] and sum(reasons.values()) == cam["pixels"]
    warnings = report["warnings"]
    assert isinstance(warnings, list)
    assert any("reflected light" in w and "not for a calibration fault" in w for w in warnings), warnings
    health = report["calibration_health"]
    assert isinstance(health, dict) and health["status"] == "ok", health


def test_mirror_groove_on_both_axes_has_no_ghost_points(folder: Path) -> None:
    # measured at 10 ms, the two copies taken apart (both axes: by the Jacobian's orientation): 0.020 % of the
    # points > 1 mm (0.007 % > 5 mm), 0.007 % beyond 5 sigma, |err|/sigma RMS 0.85, 82.4 % complete (before the
    # separation 0.044 %, 0.008 %, 0.88, 69.9 %); period 16 alone 0.157 % (0 > 5 mm), 0, 0.78 (without the check for
    # regions walled in by reflections 1.9 %, 0.17 %; without it and the visibility check 2.9 %, 1.2 %; without
    # those and the check for two copies of the pattern 11.7 %, 2.4 %)
    s = measure(scene_config("mirror_groove", axes="xy"), folder, "mgroove_xy2")
    print(s.line())
    assert s.over_1mm <= 1e-3 and s.over_5mm <= 2e-4, s.line()
    assert s.completeness >= 0.8, s.line()
    _sigma_is_honest(s)
