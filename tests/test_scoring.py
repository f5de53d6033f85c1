"""The `score` stage: synthesis quality measured on relit images, checked on syntheses of known quality.

The exemplar is a 32 x 32 procedural material under 8 lights.  Against it we score, at 64 x 64:

- *genuine*: random 16 x 16 blocks of the exemplar, one coordinate map replayed on the whole stack (a
  reflectance-function synthesis, as a quilting synthesizer without overlap would give);
- *shuffled*: the same with 4 x 4 blocks (a poor synthesis: every patch straddles seams);
- *blurred*: the exemplar tiled 2 x 2 and blurred (sigma 1.5 texels);
- *noise*: the tiled exemplar's texels randomly permuted (the same colour histogram, no structure);
- *independent*: a genuine synthesis per light, each light with its own random map (a 2D synthesis per image).
"""
from __future__ import annotations


import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from btforge.buffers import CoordMap, SampleStack, Scores
from btforge.context import StageContext
from btforge.errors import BtforgeInputError
from btforge.plugins.demo.procedural import hemisphere_lights, make_material, render_lights
from btforge.plugins.synth import materialize
from btforge.plugins.synth.jumpmap import jumpmap
from btforge.plugins.synth.kcoherence import kcoherence
from btforge.plugins.synth.quilting import quilt
from btforge.plugins.synth.scoring import STAGES, score
from btforge.stages import RunPaths

SIZE, OUT, N_LIGHT = 32, 64, 8
TOP = np.array([[0.0, 0.0, 1.0]])


def block_coords(out_size: int, block: int, src_size: int, rng: np.random.Generator) -> CoordMap:
    """A map copying random ``block x block`` pieces of the exemplar side by side (the last ones cut)."""
    coords = np.empty((out_size, out_size, 2), np.int32)
    rows, cols = np.mgrid[0:block, 0:block]
    for r in range(0, out_size, block):
        for c in range(0, out_size, block):
            r0, c0 = rng.integers(0, src_size - block + 1, size=2)
            h, w = min(block, out_size - r), min(block, out_size - c)
            coords[r:r + h, c:c + w, 0] = r0 + rows[:h, :w]
            coords[r:r + h, c:c + w, 1] = c0 + cols[:h, :w]
    return CoordMap(coords, (src_size, src_size))


def replay(coords: CoordMap, source):
    return materialize(coords=coords, source=source)["output"]


def values(**kwargs) -> dict:
    return score(**kwargs)["scores"].values


@pytest.fixture(scope="module")
def case():
    lights = hemisphere_lights(N_LIGHT)
    material = make_material(SIZE, SIZE, bumps=12, seed=3)
    exemplar = SampleStack(render_lights(material, lights)[None], lights, TOP)
    rng = np.random.default_rng(0)
    genuine_map = block_coords(OUT, 16, SIZE, rng)
    shuffled_map = block_coords(OUT, 4, SIZE, rng)
    tiled = np.tile(exemplar.samples, (1, 1, 2, 2, 1))
    blurred = gaussian_filter(tiled, (0, 0, 1.5, 1.5, 0), mode="wrap").astype(np.float32)
    texels = tiled.reshape(N_LIGHT, OUT * OUT, 3)[:, rng.permutation(OUT * OUT)]
    per_light = np.stack([replay(block_coords(OUT, 16, SIZE, np.random.default_rng(100 + i)), exemplar).samples[0, i]
                          for i in range(N_LIGHT)])
    return {
        "exemplar": exemplar,
        "genuine_map": genuine_map,
        "shuffled_map": shuffled_map,
        "genuine": replay(genuine_map, exemplar),
        "shuffled": replay(shuffled_map, exemplar),
        "blurred": SampleStack(blurred, lights, TOP),
        "noise": SampleStack(texels.reshape(1, N_LIGHT, OUT, OUT, 3).copy(), lights, TOP),
        "independent": SampleStack(per_light[None], lights, TOP),
    }


@pytest.fixture(scope="module")
def scored(case):
    return {name: values(output=case[name], exemplar=case["exemplar"])
            for name in ("genuine", "shuffled", "blurred", "noise", "independent")}


def test_stage_is_exposed():
    assert STAGES == [score]
    assert score.name == "synth.score" and set(score.inputs) == {"output", "exemplar", "coords", "tiles"}
    assert score.optional_inputs == {"output", "coords", "tiles"} and score.outputs == {"scores": "Scores"}
    assert {"lights", "patch", "scales", "seed", "block", "wrap"} <= {p.name for p in score.params}


def test_genuine_synthesis_ranks_best(scored):
    # Genuine beats every bad synthesis on all three statistics; noise is the worst on coherence and completeness.
    print({name: {k: round(v[k], 4) for k in ("swd", "coherence", "completeness")} for name, v in scored.items()})
    for metric in ("swd", "coherence", "completeness"):
        for bad in ("shuffled", "blurred", "noise"):
            assert scored["genuine"][metric] < scored[bad][metric], (metric, bad)
    for metric in ("coherence", "completeness"):
        assert scored["noise"][metric] > max(scored[n][metric] for n in ("genuine", "shuffled", "blurred"))
    assert scored["genuine"]["scales_used"] == 3 and scored["genuine"]["lights"] == N_LIGHT


def test_exact_copy_scores_zero_distance(case):
    v = values(output=case["exemplar"], exemplar=case["exemplar"])
    assert v["swd"] == 0 and v["coherence"] == 0 and v["completeness"] == 0
    assert v["consistency"] == 1 and v["verbatim_share"] == 1
    # An 8-bit capture is decoded to linear radiance first.
    from btforge.buffers import linear_to_srgb
    srgb8 = SampleStack(np.round(linear_to_srgb(case["exemplar"].samples) * 255).astype(np.uint8),
                        case["exemplar"].lights, TOP, encoding="srgb8")
    v = values(output=replay(case["genuine_map"], srgb8), exemplar=srgb8)
    assert v["consistent"] is True and v["swd"] < 0.06


def test_independent_per_light_synthesis_is_inconsistent(case, scored):
    assert scored["genuine"]["consistent"] is True and scored["genuine"]["consistency"] >= 0.9
    assert scored["independent"]["consistent"] is False and scored["independent"]["consistency"] <= 0.2
    # The independent images are each as good as the genuine ones: only consistency tells them apart.
    assert scored["independent"]["coherence"] < scored["shuffled"]["coherence"]
    # With the map, consistency is exact: every texel of the genuine output is the texel the map names.
    with_map = values(output=case["genuine"], exemplar=case["exemplar"], coords=case["genuine_map"])
    assert with_map["consistency"] == 1 and with_map["consistency_method"] == "coords"
    wrong_map = values(output=case["independent"], exemplar=case["exemplar"], coords=case["genuine_map"])
    assert wrong_map["consistent"] is False


def test_consistency_patch_traces_small_copied_pieces(case, scored):
    # 4 x 4 pieces are smaller than the 7 x 7 patches, so only a smaller consistency patch can trace them.
    assert scored["shuffled"]["consistency"] < 0.5
    small = values(output=case["shuffled"], exemplar=case["exemplar"], consistency_patch=3)
    assert small["consistency"] >= 0.8 and small["consistent"] is True
    independent = values(output=case["independent"], exemplar=case["exemplar"], consistency_patch=3)
    assert independent["consistency"] <= 0.2


def test_seam_ratio(case):
    ex = case["exemplar"]
    copy = values(output=ex, exemplar=ex, block=4)
    shuffled = values(output=case["shuffled"], exemplar=ex, block=4)
    assert 0.8 <= copy["seam_ratio"] <= 1.25 and copy["seam_source"] == "block grid"
    assert shuffled["seam_ratio"] > 2.0
    # Without a block size the map's discontinuities are the seams.
    from_map = values(output=case["shuffled"], exemplar=ex, coords=case["shuffled_map"])
    assert from_map["seam_source"] == "coords" and from_map["seam_ratio"] > 2.0
    # The procedural material tiles, so its wrap-around boundary is invisible.
    wrapped = values(output=ex, exemplar=ex, wrap=True)
    assert wrapped["seam_source"] == "wrap" and 0.8 <= wrapped["seam_ratio"] <= 1.25
    assert values(output=ex, exemplar=ex)["seam_ratio"] is None


def test_verbatim_share(case):
    ex = case["exemplar"]
    identity = CoordMap(np.stack(np.mgrid[0:SIZE, 0:SIZE], axis=-1).astype(np.int32), (SIZE, SIZE))
    assert values(output=ex, exemplar=ex, coords=identity)["verbatim_share"] == 1
    assert values(output=ex, exemplar=ex)["verbatim_share"] == 1
    assert values(output=case["shuffled"], exemplar=ex)["verbatim_share"] == 0
    assert values(output=case["shuffled"], exemplar=ex, coords=case["shuffled_map"])["verbatim_share"] == 0
    # 24 x 24 pieces are larger than a quarter of the exemplar (256 texels); the cut 16 x 16 corner is not.
    big_map = block_coords(OUT, 24, SIZE, np.random.default_rng(5))
    big = replay(big_map, ex)
    exact = values(output=big, exemplar=ex, coords=big_map)
    estimated = values(output=big, exemplar=ex)
    assert exact["verbatim_share"] == pytest.approx(1 - 16 * 16 / OUT ** 2)
    assert estimated["verbatim_share"] == pytest.approx(exact["verbatim_share"], abs=0.02)
    assert estimated["verbatim_method"] == "patch matches"


def test_blended_map_replays_exactly(case):
    ex = case["exemplar"]
    base = case["genuine_map"]
    other = np.roll(base.coords, 1, axis=1)
    weight = np.random.default_rng(1).uniform(0, 1, base.coords.shape[:2]).astype(np.float32)
    blended = CoordMap(base.coords, base.source_size, np.ascontiguousarray(other), weight)
    out = replay(blended, ex)
    assert values(output=out, exemplar=ex, coords=blended)["consistency"] == 1


@pytest.fixture(scope="module")
def synthesized(case):
    """Real synthesizer outputs at 64 x 64 from the test exemplar: name -> (coordinate map, materialized stack)."""
    ex = case["exemplar"]
    # "quilt": the quilter's own blocks (refinement moves single texels, which a trace without the map cannot follow)
    runs = {"quilt": (quilt, dict(block=16, overlap=3, seam="cut", refine=0)),
            "quilt_blend": (quilt, dict(block=16, overlap=3, seam="blend")),
            "kcoherence": (kcoherence, dict(levels=2)),
            "jumpmap": (jumpmap, {})}
    out = {}
    for name, (stage, params) in runs.items():
        coords = stage(exemplar=ex, size=[OUT, OUT], seed=1, **params)["coords"]
        out[name] = (coords, replay(coords, ex))
    return out


def test_real_synthesizer_outputs_are_consistent_with_their_maps(case, synthesized):
    for name, (coords, output) in synthesized.items():
        v = values(output=output, exemplar=case["exemplar"], coords=coords)
        assert v["consistency"] == 1 and v["consistent"] is True, name
    # The map must matter: another synthesizer's map does not explain this output.
    v = values(output=synthesized["jumpmap"][1], exemplar=case["exemplar"], coords=synthesized["quilt"][0])
    assert v["consistent"] is False


def test_quilted_output_ranks_above_the_baselines(case, scored, synthesized):
    # Measured on this exemplar (map-free): quilt swd 0.041, coherence 0.077, completeness 0.032; the best
    # baseline values are 0.049 (shuffled), 0.094 (blurred) and 0.125 (blurred).
    for name in ("quilt", "quilt_blend"):
        coords, output = synthesized[name]
        v = values(output=output, exemplar=case["exemplar"])
        for metric in ("swd", "coherence", "completeness"):
            for bad in ("shuffled", "blurred", "noise"):
                assert v[metric] < scored[bad][metric], (name, metric, bad)
        if name == "quilt":
            assert v["consistent"] is True  # quilt copies blocks wide enough to be traced without the map


def noisy_ptm(exemplar, space: str):
    """An rgb PTM fitted to the exemplar with coefficient noise large enough that many texels evaluate below 0
    (clamped) at some light, in ``space``."""
    from btforge.plugins.ptm.model import PTMModel, fit_ptm
    model, _ = fit_ptm(exemplar)
    noise = np.random.default_rng(4).normal(0, 1.0, model.coeffs.shape) * model.coeffs.std(axis=(0, 1))
    coeffs = (model.coeffs + noise).astype(np.float32)
    return PTMModel(coeffs, model.albedo, "rgb", space, model.channel_names, model.basis)


@pytest.mark.parametrize("kind", ["ptm_linear", "ptm_srgb", "srgb8"])
def test_blended_quilt_is_consistent_where_evaluation_is_not_linear(case, kind):
    # Blending relit radiance would not reproduce these: a clamped polynomial, a polynomial of sRGB values, and
    # 8-bit codes re-encoded after blending.  The score replays the map as materialize does, so all are exact,
    # even at tolerance 0.
    from btforge.buffers import linear_to_srgb8
    ex = case["exemplar"]
    if kind == "srgb8":
        exemplar = SampleStack(linear_to_srgb8(ex.samples), ex.lights, TOP, encoding="srgb8")
    else:
        exemplar = noisy_ptm(ex, "linear" if kind == "ptm_linear" else "srgb")
        relit = exemplar.evaluate(ex.lights, engine="numpy")
        if kind == "ptm_linear":
            assert (relit == 0).mean() > 0.05  # the clamp is really exercised
    # the quilter's own blends (refinement keeps a blend only where the refined source stays: fewer blended texels)
    coords = quilt(exemplar=exemplar, size=[OUT, OUT], block=12, overlap=3, seam="blend", seed=2, refine=0)["coords"]
    assert coords.blend_weight.size and ((coords.blend_weight > 0) & (coords.blend_weight < 1)).mean() > 0.2
    output = replay(coords, exemplar)
    v = values(output=output, exemplar=exemplar, coords=coords, lights=ex.lights.tolist(), tolerance=0.0)
    assert v["consistency"] == 1 and v["consistent"] is True


def test_wrap_follows_the_wired_map(case):
    ex = case["exemplar"]
    coords = quilt(exemplar=ex, size=[OUT, OUT], block=16, overlap=3, wrap=True, seed=1)["coords"]
    assert coords.wrap is True
    output = replay(coords, ex)
    from_map = values(output=output, exemplar=ex, coords=coords)
    assert from_map["wrap"] is True and from_map["seam_source"] == "coords + wrap"
    told = values(output=output, exemplar=ex, coords=coords, wrap=False)
    assert told["wrap"] is False and told["seam_source"] == "coords"
    assert values(output=output, exemplar=ex)["wrap"] is False


def test_deterministic_by_seed(case):
    a = values(output=case["genuine"], exemplar=case["exemplar"], seed=7)
    b = values(output=case["genuine"], exemplar=case["exemplar"], seed=7)
    c = values(output=case["genuine"], exemplar=case["exemplar"], seed=8)
    assert a == b
    assert a["swd"] != c["swd"]


def test_models_and_lights(case, tmp_path):
    from btforge.plugins.ptm.model import fit_ptm
    ex = case["exemplar"]
    model, _ = fit_ptm(ex)
    out_model = replay(case["genuine_map"], model)
    # Two models: relit at probe lights; model against stack: at the exemplar stack's lights.
    both = values(output=out_model, exemplar=model)
    assert both["lights_source"] == "8 probe lights" and both["consistent"] is True
    mixed = values(output=out_model, exemplar=ex)
    assert mixed["lights_source"] == "exemplar" and mixed["lights"] == N_LIGHT
    # Lights from a .lp file, resolved against the graph's folder; a subset of the stack's lights is fine.
    lp = tmp_path / "lights.lp"
    lp.write_text("3\n" + "".join(f"img{i}.png {x:.7f} {y:.7f} {z:.7f}\n" for i, (x, y, z) in enumerate(ex.lights[:3])))
    ctx = StageContext(node="score", paths=RunPaths(tmp_path, tmp_path))
    result = score(ctx, output=case["genuine"], exemplar=ex, lights="lights.lp")
    assert isinstance(result["scores"], Scores) and result["scores"].values["lights"] == 3
    assert ctx.notes["consistency"] == result["scores"].values["consistency"]
    assert {"swd", "coherence", "completeness", "verbatim_share", "seam_ratio", "consistent"} <= set(ctx.notes)


def test_invalid_inputs(case):
    ex = case["exemplar"]
    grey = SampleStack(ex.samples[..., :1].copy(), ex.lights, TOP, channels=("Y",))
    with pytest.raises(BtforgeInputError, match="same channels"):
        score(output=grey, exemplar=ex)
    with pytest.raises(BtforgeInputError, match="missing"):
        score(output=case["genuine"], exemplar=ex, lights=[[0.6, 0.0, 0.8]])
    with pytest.raises(BtforgeInputError, match="missing"):
        score(output=SampleStack(case["genuine"].samples[:, :4].copy(), ex.lights[:4], TOP), exemplar=ex)
    with pytest.raises(BtforgeInputError, match="output's size"):
        score(output=case["genuine"], exemplar=ex, coords=CoordMap(np.zeros((8, 8, 2), np.int32), (SIZE, SIZE)))
    with pytest.raises(BtforgeInputError, match="exemplar"):
        score(output=case["genuine"], exemplar=ex, coords=CoordMap(np.zeros((OUT, OUT, 2), np.int32), (16, 16)))
    with pytest.raises(BtforgeInputError, match="patch"):
        score(output=case["genuine"], exemplar=ex, patch=40)


def test_sliced_wasserstein_of_several_outputs_gives_each_its_own_figures():
    """``synth.score`` measures the output and the shuffled-block baselines against one exemplar analysis; each
    output's distances must be those a call of its own gives, whatever is measured beside it (outputs of other
    sizes too, one too small for the coarsest level)."""
    from btforge.plugins.synth.scoring import sliced_wasserstein_levels, sliced_wasserstein_of_outputs
    rng = np.random.default_rng(3)
    exemplar = rng.random((2, 40, 36, 3)).astype(np.float32)
    outputs = [(rng.random((2, 70, 64, 3)).astype(np.float32), False),
               (np.zeros((2, 50, 80, 3), np.float32), True),                  # constant: the hard case of sorting
               (np.tile(exemplar, (1, 2, 2, 1)), False),                      # a copy: close to the exemplar
               (rng.random((2, 12, 30, 3)).astype(np.float32), False)]        # too small for the third level
    for group in (outputs, outputs[::-1]):
        together = sliced_wasserstein_of_outputs(exemplar, group, patch=5, scales=3, projections=32, seed=4)
        for (image, wrap), levels in zip(group, together):
            alone = sliced_wasserstein_levels(exemplar, image, patch=5, scales=3, projections=32, seed=4, wrap=wrap)
            assert levels == alone
            assert 1 <= len(alone) <= 3 and all(np.isfinite(alone)) and min(alone) >= 0
    assert [len(levels) for levels in together] == [2, 3, 3, 3]
