"""XOR codes (``sequence.code: xor``) on the virtual rig's scenes, rendered into a manifest with ``xor_with``
frames and reconstructed by ``scan3d decode``, against the exact truth (see ``hard_scenes.py``).

Measured when written (camera 480x384, Gray stripe 8 + phase period 16; plain Gray / XOR on base bit 0):

| scene | complete | RMS | > 1 mm |
|---|---|---|---|
| default | 97.7 / 91.1 % | 0.108 / 0.108 mm | 0.001 / 0.001 % |
| diffuse groove (8 bounce samples) | 97.7 / 91.9 % | 0.254 / 0.249 mm | 0.75 / 0.69 % |
| mirror groove | 92.2 / 81.8 % | 94 / 94 mm | 17.2 / 14.2 % |

On base bit 1 the default scene is 94.1 % complete, on bit 2 95.8 %. XOR costs completeness: a pixel within a
few tenths of a projector px of an edge of the base bit (where every XOR frame equals its inverse as nearly as
the base frame does) cannot tell which side of the edge its XOR bits belong to and is dropped (1.7 % of the
lit pixels here, an edge every 16 projector px), and the 8-neighbour filter then drops its neighbours' points
too. On the diffuse groove the plain Gray code decodes no bit wrong (every coordinate within 2 projector px of
the truth); its points > 1 mm come from the phase, biased by the sampled bounce light (0.23 % with 32 samples
instead of 8), so no Gray code family changes them.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import pytest
import yaml
from hard_scenes import SceneStats, measure, scene_text

from appliance import cli
from appliance.config import AppConfig, parse_config

SIGMA_RMS = (0.7, 1.4)


def xor_config(scene: str, base: int = 0, **kwargs: float) -> AppConfig:
    """A hard scene's config with its Gray code projected as XOR codes on Gray bit ``base``."""
    text = scene_text(scene, **kwargs)  # type: ignore[arg-type]
    assert "  kind: gray_phase\n" in text
    text = text.replace("  kind: gray_phase\n", f"  kind: gray_phase\n  code: xor\n  xor_base_bit: {base}\n")
    return parse_config(text, f"{scene}-xor.yaml")


def _sigma_is_honest(s: SceneStats) -> None:
    assert SIGMA_RMS[0] <= s.z_rms <= SIGMA_RMS[1], s.line()
    assert s.over_5sigma <= 1e-3, s.line()


def test_scan3d_decode_of_an_xor_manifest_holds_the_default_scene(tmp_path: Path) -> None:
    s = measure(xor_config("default"), tmp_path, "xor")
    print(s.line())
    frames = yaml.safe_load((tmp_path / "xor.yaml").read_text())["frames"]
    xors = [f for f in frames if f.get("pattern") == "gray" and "xor_with" in f]
    assert len(xors) == 14 and {f["xor_with"] for f in xors} == {0}  # bits 1..7, each with its inverse
    assert s.over_1mm <= 1e-4 and s.rms_mm <= 0.15, s.line()
    assert s.completeness >= 0.89, s.line()  # plain Gray: 97.7 %; see the module docstring
    _sigma_is_honest(s)


def test_scan3d_scan_streams_xor_codes_on_the_virtual_rig(tmp_path: Path) -> None:
    # the service's path: the virtual rig renders the XOR frames, the streaming decoder decodes them as they come
    text = scene_text("default").replace("  kind: gray_phase\n", "  kind: gray_phase\n  code: xor\n")
    (tmp_path / "xor.yaml").write_text(text)
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = cli.main(["scan", "--config", str(tmp_path / "xor.yaml"), "--out", str(tmp_path / "o")])
    assert rc == 0, out.getvalue()
    (sidecar,) = (tmp_path / "o").glob("*/*.json")
    meta = json.loads(sidecar.read_text())
    assert "xor bit 0" in meta["sequence"]["description"] and meta["sequence"]["frames"] == 26
    truth = meta["extra"]["ground_truth"]
    assert truth["rms_mm"] <= 0.15 and truth["share_over_1mm"] <= 1e-4, truth
    assert truth["completeness"] >= 0.89, truth  # measured 91.2 %


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="measured 0.69 % of the points > 1 mm (plain Gray 0.75 %), 91.9 % complete: "
                   "the sampled one-bounce light biases the phase (the plain Gray code has no wrong bit there: "
                   "every decoded coordinate within 2 projector px), which no choice of Gray code changes")
def test_xor_codes_hold_the_diffuse_groove(tmp_path: Path) -> None:
    s = measure(xor_config("diffuse_groove", bounce=8), tmp_path, "dgroove")
    print(s.line())
    assert s.completeness >= 0.97 and s.over_1mm <= 1e-3, s.line()
    _sigma_is_honest(s)


def test_a_base_bit_without_a_coarser_bit_is_one_clear_line(tmp_path: Path) -> None:
    # 1280 px in stripes of 8 px: 8 Gray bits, so the base can be bit 0..6
    (tmp_path / "bad.yaml").write_text("sequence:\n  kind: gray_phase\n  code: xor\n  xor_base_bit: 7\n")
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = cli.main(["scan", "--config", str(tmp_path / "bad.yaml"), "--out", str(tmp_path / "o")])
    text = out.getvalue()
    assert rc != 0 and "Traceback" not in text
    assert "sequence.xor_base_bit = 7: gray code axis x: xor base bit 7: must be in 0..6" in text, text
    assert "choose a lower base bit" in text
