"""A frozen vision tower encodes each training grid once (labrobfail_vlm/train/tower_cache.py): same outputs as
the tower itself, served again on later epochs, never for a tower that trains."""

import json

import pytest
import torch
from conftest import run_here
from test_train import small_ds, tiny, tiny_train  # noqa: F401 - session fixtures

from labrobfail_vlm.train.tower_cache import TowerCache, cache_frozen_tower, inference_cache


def _frozen(tiny):  # noqa: F811
    from labrobfail_vlm.model.loading import load_model

    model = load_model(tiny).eval()
    model.requires_grad_(False)
    return model


def _grids(tiny, small_ds, n):  # noqa: F811
    """Pixels and grid sizes of the first n training trajectories' grids (one image each)."""
    from labrobfail_vlm.model.loading import load_processor
    from labrobfail_vlm.train.data import Collator
    from labrobfail_vlm.train.packing import TrajectoryDataset

    proc = load_processor(tiny)
    proc.tokenizer.padding_side = "right"
    td = TrajectoryDataset(small_ds, "train")
    b = Collator(proc, 1024)([td[i] for i in range(n)])
    return b["pixel_values"], b["image_grid_thw"]


def _features(model, px, thw):
    with torch.no_grad():
        out = model.model.get_image_features(px, thw)
    return torch.cat(out.pooler_output)


def test_cached_outputs_equal_the_towers_and_do_not_depend_on_the_batch(tiny, small_ds):  # noqa: F811
    px, thw = _grids(tiny, small_ds, 3)
    model = _frozen(tiny)
    want = _features(model, px, thw)
    cache = cache_frozen_tower(model, 64)
    assert isinstance(cache, TowerCache)
    got = _features(model, px, thw)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    assert (cache.misses, cache.hits, cache.stats()["stored"]) == (3, 0, 3)
    assert torch.equal(_features(model, px, thw), got)  # a later epoch: served, the very same numbers
    assert (cache.misses, cache.hits) == (3, 3)
    # the second image alone, then first and second swapped: the rows follow the images, not their positions
    per = (thw.prod(-1) // 4).tolist()
    rows = torch.split(got, per)
    n0, n1 = int(thw[0].prod()), int(thw[1].prod())
    swapped = torch.cat([px[n0 : n0 + n1], px[:n0]])
    assert torch.equal(_features(model, swapped, thw[[1, 0]]), torch.cat([rows[1], rows[0]]))
    # different pixels are a miss, never a stale value
    other = _features(model, px[:n0] + 0.5, thw[:1])
    assert cache.misses == 4 and not torch.allclose(other, rows[0])
    # a bfloat16 tower (a real Qwen3-VL's dtype) is cached too: its pixels have no numpy dtype
    model = _frozen(tiny).to(torch.bfloat16)
    cache = cache_frozen_tower(model, 64)
    assert torch.equal(_features(model, px, thw), _features(model, px, thw)) and cache.hits == 3


def test_the_memory_bound_holds_and_a_training_tower_is_never_cached(tiny, small_ds):  # noqa: F811
    px, thw = _grids(tiny, small_ds, 2)
    model = _frozen(tiny)
    cache = cache_frozen_tower(model, 1e-9)  # room for nothing: every call encodes again
    _features(model, px, thw)
    _features(model, px, thw)
    assert (cache.misses, cache.hits, cache.bytes) == (4, 0, 0)
    assert cache_frozen_tower(_frozen(tiny), 0) is None
    model = _frozen(tiny)
    model.model.visual.merger.requires_grad_(True)
    assert cache_frozen_tower(model, 64) is None
    with pytest.raises(ValueError, match="trains"):
        TowerCache(model.model.visual, 64)


def test_checkpoints_with_one_tower_share_its_outputs_and_another_tower_does_not(tiny, small_ds):  # noqa: F811
    """The learning curve's models (inference_cache): a second model with the same tower weights serves the first's
    outputs without encoding; a tower whose weights differ by one value starts empty."""
    from labrobfail_vlm.model.loading import load_model

    px, thw = _grids(tiny, small_ds, 2)
    want = _features(_frozen(tiny), px, thw)  # the tower itself, no cache
    a = load_model(tiny).eval()
    cache_a = inference_cache(a, 64)
    torch.testing.assert_close(_features(a, px, thw), want, rtol=1e-5, atol=1e-6)
    b = load_model(tiny).eval()
    cache_b = inference_cache(b, 64, previous=cache_a)
    with torch.no_grad():  # the merged tokens and the DeepStack features alike
        got, ref = b.model.get_image_features(px, thw), a.model.get_image_features(px, thw)
    assert torch.equal(torch.cat(got.pooler_output), torch.cat(ref.pooler_output))
    levels = [(torch.cat(list(g)), torch.cat(list(r))) for g, r in zip(got.deepstack_features, ref.deepstack_features)]
    assert levels and all(torch.equal(g, r) for g, r in levels)
    assert (cache_b.misses, cache_b.hits) == (0, 2) and not any(p.requires_grad for p in b.parameters())
    c = load_model(tiny).eval()
    with torch.no_grad():
        c.model.visual.merger.linear_fc2.bias[0] += 1.0
    cache_c = inference_cache(c, 64, previous=cache_b)
    assert not torch.equal(_features(c, px, thw), want) and (cache_c.misses, cache_c.hits) == (2, 0)


def test_the_bench_encodes_each_grid_once_across_its_passes(tiny, small_ds):  # noqa: F811
    """The bench's model (labrobfail-evaluate's loader, tower_cache_mb=auto on CPU): its Q6-template pass reads the
    grids it already encoded, and its blind baseline encodes the one grey grid once; tower_cache_mb=0 caches nothing."""
    from labrobfail_vlm import questions as Q
    from labrobfail_vlm.bench import evaluate as ev
    from labrobfail_vlm.bench.cli import _load_analyzer
    from labrobfail_vlm.config import load_config
    from labrobfail_vlm.train.grounding import vision_module

    args = [f"model={tiny}", f"dataset_dir={small_ds}"]
    analyzer = _load_analyzer(load_config("evaluate.yaml", args))[0]
    cache = vision_module(analyzer.model).forward
    assert isinstance(cache, TowerCache)
    recs, traj = ev.load_split(small_ds, "test")
    n = len({Q.traj_of(r["id"]) for r in recs})
    first = ev.model_predictions(analyzer, small_ds, recs, traj, progress=False, batch_size=4)
    encoded = cache.misses
    assert 0 < encoded <= n and cache.misses + cache.hits == n
    assert ev.model_predictions(analyzer, small_ds, recs, traj, progress=False, batch_size=4) == first
    assert cache.misses == encoded and cache.hits == 2 * n - encoded
    ev.model_predictions(analyzer, small_ds, recs, traj, blind=True, progress=False, batch_size=4)
    assert cache.misses == encoded + 1
    off = _load_analyzer(load_config("evaluate.yaml", [*args, "tower_cache_mb=0"]))[0]
    assert not isinstance(vision_module(off.model).forward, TowerCache)


def test_a_frozen_tower_run_encodes_each_grid_once_and_trains_as_without_the_cache(tiny, small_ds, tmp_path):  # noqa: F811
    frozen = ["lr.vision=0", "lr.merger=0", "grounding.weight=0", "grounding.pretrain_epochs=0", "epochs=2"]
    summaries = []
    for mb in (4096, 0):
        out = tmp_path / f"mb{mb}"
        r = run_here(tiny_train(tiny, small_ds, out, *frozen, f"tower_cache_mb={mb}"))
        assert r.returncode == 0, r.stderr[-3000:]
        summaries.append(json.loads((out / "train_summary.json").read_text()))
    cached, plain = summaries
    from labrobfail_vlm.train.packing import TrajectoryDataset

    grids = len(TrajectoryDataset(small_ds, "train"))
    assert cached["tower_cache"]["misses"] <= grids and cached["tower_cache"]["hits"] >= grids  # epoch 2: all hits
    assert cached["tower_cache"]["misses"] + cached["tower_cache"]["hits"] == 2 * grids
    assert "tower_cache" not in plain
    assert cached["train_loss"] == pytest.approx(plain["train_loss"], rel=1e-5)
    r = run_here(tiny_train(tiny, small_ds, tmp_path / "bad", *frozen, "tower_cache_mb=-1"))
    assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].startswith("error: tower_cache_mb:"), r.stderr


def test_a_stored_grid_is_served_by_its_file_and_not_read_again(tiny, small_ds, tmp_path):  # noqa: F811
    import os
    import shutil

    from labrobfail_vlm.model.loading import load_processor
    from labrobfail_vlm.train.data import Collator
    from labrobfail_vlm.train.packing import TrajectoryDataset
    from labrobfail_vlm.train.tower_cache import file_key

    proc = load_processor(tiny)
    proc.tokenizer.padding_side = "right"
    td = TrajectoryDataset(small_ds, "train")
    copy = tmp_path / "grid.png"  # the second trajectory's grid, from a file this test may rewrite
    shutil.copy(td[1][0]["image"], copy)
    items = [td[0], [{**r, "image": str(copy)} for r in td[1]]]
    plain = Collator(proc, 1024)(items)
    model = _frozen(tiny)
    want = _features(model, plain["pixel_values"], plain["image_grid_thw"])
    cache = cache_frozen_tower(model, 64)
    col = Collator(proc, 1024, tower_cache=cache)
    first = col(items)
    assert first["grid_keys"] == [file_key(it[0]["image"]) for it in items]
    assert torch.equal(first["pixel_values"], plain["pixel_values"])  # a miss: the grid's own pixels
    cache.given = first["grid_keys"]
    torch.testing.assert_close(_features(model, first["pixel_values"], first["image_grid_thw"]), want)
    assert (cache.misses, cache.hits, cache.given) == (2, 0, None)  # the keys served one call
    again = col(items)  # stored: the grids are not read, their pixels are zeros nothing reads
    assert not again["pixel_values"].any() and again["pixel_values"].shape == plain["pixel_values"].shape
    assert torch.equal(again["input_ids"], plain["input_ids"]) and torch.equal(
        again["image_grid_thw"], plain["image_grid_thw"]
    )
    cache.given = again["grid_keys"]
    torch.testing.assert_close(_features(model, again["pixel_values"], again["image_grid_thw"]), want)
    assert (cache.misses, cache.hits) == (2, 2)
    st = os.stat(copy)  # a rewritten grid file is another key: read and encoded again
    os.utime(copy, ns=(st.st_atime_ns, st.st_mtime_ns + 1))
    third = col(items)
    assert third["grid_keys"][1] != first["grid_keys"][1] and third["pixel_values"][-1].any()
    # with augmentation nothing is keyed by file: every augmented grid is new
    assert Collator(proc, 1024, augment=object(), tower_cache=cache).tower_cache is None
