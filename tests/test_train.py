"""Hybrid fine-tuning on a tiny real Qwen3-VL: gradient groups, label masking, save/reload, merge, DeepSpeed."""

import json
import os
import shutil
import sys
from pathlib import Path

import pytest
import torch
from conftest import cli, free_port, run, run_here

SMALL_GRID = ["grid.width=256", "grid.height=128", "grid.max_frames=8", "grid.columns=4"]


def scratch_train(tiny, ds, out) -> list[str]:
    """train.py on the tiny preset and model from a scratch tower, on the dataset folder `ds`, written to `out`."""
    model = ["preset=tiny", "tower=scratch", f"model.path={tiny}"]
    return [sys.executable, "train.py", *model, f"dataset_dir={ds}", f"output_dir={out}"]


def tiny_train(tiny, ds, out, *extra: str) -> list[str]:
    """train.py on the tiny model from a scratch tower, batches of 2, no wandb or progress bars; `extra` wins."""
    quiet = ["global_batch=2", "per_device_batch=2", "wandb.enabled=false", "progress=false"]
    return [*scratch_train(tiny, ds, out), *quiet, *extra]


@pytest.fixture(scope="session")
def tiny(tmp_path_factory):
    from labrobfail_vlm.model.tiny import build_tiny

    return build_tiny(tmp_path_factory.mktemp("m") / "tiny")


@pytest.fixture(scope="session")
def small_ds(run6, tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "small"
    r = run([cli("build-dataset"), f"shards={run6}", f"out_dir={out}", "progress=false", *SMALL_GRID], 300)
    assert r.returncode == 0, r.stderr
    return out


def batch(tiny, small_ds, n=2):
    from labrobfail_vlm.model.loading import load_processor
    from labrobfail_vlm.train.data import Collator, VQADataset

    proc = load_processor(tiny)
    proc.tokenizer.padding_side = "right"
    ds = VQADataset(small_ds, "train")
    return proc, Collator(proc, 512)([ds[i] for i in range(n)])


def test_labels_cover_exactly_the_answer(tiny, small_ds):
    proc, b = batch(tiny, small_ds, n=3)
    from labrobfail_vlm.train.data import VQADataset

    ds = VQADataset(small_ds, "train")
    for i in range(3):
        kept = b["labels"][i][b["labels"][i] != -100]
        assert proc.tokenizer.decode(kept) == ds[i]["answer"] + "<|im_end|>\n"
    assert (b["input_ids"] == proc.image_token_id).sum() == 3 * 32  # 256x128 grid: 8x4 visual tokens each


def test_record_loss_weights_each_record_equally(tiny, small_ds):
    from labrobfail_vlm.model.loading import load_model
    from labrobfail_vlm.train.data import Collator, VQADataset
    from labrobfail_vlm.train.trainer import record_loss

    proc, _ = batch(tiny, small_ds)
    ds = VQADataset(small_ds, "train")
    q2 = next(ds[i] for i in range(len(ds)) if ds[i]["id"].endswith("_Q2"))
    q6 = next(ds[i] for i in range(len(ds)) if ds[i]["id"].endswith("_Q6"))
    b = Collator(proc, 512, {"Q2": 3.0})([q2, q6])
    assert b.pop("record_weight").tolist() == [3.0, 1.0]
    model = load_model(tiny).eval()
    with torch.no_grad():
        alone = [model(**Collator(proc, 512)([r]), use_cache=False).loss for r in (q2, q6)]  # HF token mean
        ours, _ = record_loss(
            model, {k: v for k, v in b.items() if k != "labels"}, b["labels"], torch.tensor([3.0, 1.0])
        )
        token_mean = model(**b).loss
    assert ours == pytest.approx(float(3 * alone[0] + alone[1]) / 2, rel=1e-4)
    # HF's token mean lets the ~30-token correction outweigh the 3-token Yes/No answer; the record loss does not
    n2, n6 = [int((Collator(proc, 512)([r])["labels"] != -100).sum()) for r in (q2, q6)]
    assert n6 > 3 * n2
    assert float(token_mean) == pytest.approx(float(n2 * alone[0] + n6 * alone[1]) / (n2 + n6), rel=1e-4)


def test_answer_balance_evens_out_the_answers_of_a_question(tiny):
    from labrobfail_vlm.config import ConfigError
    from labrobfail_vlm.model.loading import load_processor
    from labrobfail_vlm.train.data import Collator, answer_balance

    def rec(i: int, dim: str, answer: str) -> dict:
        return {"id": f"seen-ep{i:07d}_{dim}", "question": "q", "answer": answer}

    severities = ["2"] * 6 + ["3"] * 3 + ["1"]  # six Dangerous, three Fatal, one Risk
    raw = [rec(i, "Q4", a) for i, a in enumerate(severities)] + [rec(0, "Q2", "Yes"), rec(1, "Q2", "No")]
    full = answer_balance(raw, {"Q4": 1.0, "Q2": 0.0})
    assert set(full) == {"Q4"}  # p = 0 leaves a question alone
    w = full["Q4"]
    assert sum(w[a] for a in severities) == pytest.approx(len(severities))  # the question keeps its mean weight 1
    assert 6 * w["2"] == pytest.approx(3 * w["3"]) == pytest.approx(w["1"])  # p = 1: every answer the same total
    half = answer_balance(raw, {"Q4": 0.5})["Q4"]
    assert w["2"] < half["2"] < 1.0 < half["1"] < w["1"]
    for bad in ({"Q4": 1.5}, {"Q9": 0.5}, {"Q5": 0.5}):  # out of range, no such question, no Q5 records
        with pytest.raises(ConfigError, match="loss.balance"):
            answer_balance(raw, bad)
    proc = load_processor(tiny)
    col = Collator(proc, 512, {"Q4": 2.0}, answer_weights=full)
    assert col.weight({"id": "seen-ep0000001_Q4", "answer": "1"}) == pytest.approx(2.0 * w["1"])
    assert col.weight({"id": "seen-ep0000001_Q2", "answer": "No"}) == 1.0
    with pytest.raises(ConfigError, match="mode=record"):
        Collator(proc, 512, None, answer_weights=full)


@pytest.mark.parametrize(
    "mode,expect",
    [("hybrid", {"vision", "merger", "lora"}), ("frozen_vision", {"lora"}), ("full", {"vision", "merger", "text"})],
)
def test_gradients_reach_exactly_the_intended_groups(tiny, small_ds, mode, expect):
    from labrobfail_vlm.model.hybrid import apply_tuning, group_of
    from labrobfail_vlm.model.loading import load_model

    _, b = batch(tiny, small_ds)
    model = apply_tuning(load_model(tiny), mode, {"r": 8, "alpha": 16, "dropout": 0.0})
    if mode != "full":  # LoRA B starts at zero; nudge it so gradients reach A as well
        for n, p in model.named_parameters():
            if "lora_B" in n:
                torch.nn.init.normal_(p, std=0.02)
    model(**b).loss.backward()
    got = {}
    for n, p in model.named_parameters():
        g = group_of(n)
        has = p.grad is not None and bool(p.grad.abs().sum() > 0)
        got.setdefault(g, []).append(has)
        if not p.requires_grad:
            assert p.grad is None, n
    flowing = {g for g, v in got.items() if any(v)}
    assert flowing == expect
    for g in expect:  # every tensor of an intended group gets a gradient (deepstack mergers included)
        assert sum(got[g]) >= 0.9 * len(got[g]), (g, sum(got[g]), len(got[g]))


def test_save_reload_identical_logits_and_merge(tiny, small_ds, tmp_path):
    from transformers import Qwen3VLForConditionalGeneration, TrainingArguments

    from labrobfail_vlm.model.hybrid import apply_tuning
    from labrobfail_vlm.model.loading import load_model
    from labrobfail_vlm.train.checkpoint import load_finetuned
    from labrobfail_vlm.train.data import Collator, VQADataset
    from labrobfail_vlm.train.trainer import HybridTrainer

    proc, b = batch(tiny, small_ds)
    model = apply_tuning(load_model(tiny), "hybrid", {"r": 8, "alpha": 16, "dropout": 0.0})
    args = TrainingArguments(
        output_dir=str(tmp_path / "run"),
        per_device_train_batch_size=2,
        max_steps=2,
        report_to="none",
        use_cpu=True,
        remove_unused_columns=False,
        disable_tqdm=True,
        save_strategy="no",
        learning_rate=1e-3,
    )
    tr = HybridTrainer(
        model=model,
        args=args,
        train_dataset=VQADataset(small_ds),
        data_collator=Collator(proc, 512),
        processing_class=proc,
        group_lrs={"vision": 1e-3, "merger": 1e-3, "lora": 1e-3, "text": 0},
        base_model=str(tiny),
        tuning="hybrid",
        grid=json.loads((small_ds / "stats.json").read_text())["grid"],
    )
    assert [g["lr"] for g in tr.create_optimizer().param_groups] == [1e-3, 1e-3, 1e-3]
    tr.train()
    tr.save_model(str(tmp_path / "ck"))
    model.eval()
    with torch.no_grad():
        ref = model(**b).logits
        again = load_finetuned(tmp_path / "ck").eval()(**b).logits
    assert torch.equal(ref, again)
    base = load_model(tiny).eval()
    with torch.no_grad():
        assert not torch.allclose(base(**b).logits, ref)  # training changed the model
    r = run([sys.executable, "scripts/merge.py", f"src={tmp_path / 'ck'}", f"out={tmp_path / 'merged'}"], 300)
    assert r.returncode == 0, r.stderr
    merged = Qwen3VLForConditionalGeneration.from_pretrained(tmp_path / "merged").eval()
    with torch.no_grad():
        assert (merged(**b).logits - ref).abs().max() < 1e-5
    assert (tmp_path / "merged" / "chat_template.jinja").is_file()
    # inference rebuilds the grid the checkpoint was trained on (SMALL_GRID: 8 keyframes, 4 per band)
    from labrobfail_vlm.analyzer import FailureAnalyzer
    from labrobfail_vlm.grid import GridConfig

    g = FailureAnalyzer.from_pretrained(tmp_path / "ck").grid
    assert g == GridConfig(width=256, height=128, max_frames=8, columns=4)
    assert FailureAnalyzer.from_pretrained(tiny).grid == GridConfig()  # a base model: the paper's default


def test_bad_train_config_is_one_line(small_ds, tmp_path):
    for args, field in [
        (["preset=huge"], "preset"),
        ([f"dataset_dir={tmp_path}"], "dataset_dir"),
        (["preset=no_index", f"dataset_dir={small_ds}"], "grid_index"),
        (["model.path=/nonexistent", f"dataset_dir={small_ds}"], "model.path"),
        (["loss.mode=sum", f"dataset_dir={small_ds}"], "loss.mode"),
        (["curriculum.detect_first=1.5", f"dataset_dir={small_ds}"], "curriculum.detect_first"),
        (["curriculum.detect_first=0.5", "loss.mode=token", f"dataset_dir={small_ds}"], "curriculum.detect_first"),
    ]:
        call = run if field == "preset" else run_here  # the first case as a real process, the rest in this one
        r = call([sys.executable, "train.py", f"output_dir={tmp_path}/o", *args])
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert field in r.stderr.strip().splitlines()[-1]
    # A run's random base left by an earlier run with another decoder size is refused, not trained unseen.
    base = tmp_path / "re" / "tiny_base"
    base.mkdir(parents=True)
    (base / "config.json").write_text(json.dumps({"text_config": {"num_hidden_layers": 2, "hidden_size": 128}}))
    args = ["preset=tiny", "tiny_arch.text.num_hidden_layers=4", f"dataset_dir={small_ds}"]
    r = run_here([sys.executable, "train.py", f"output_dir={tmp_path}/re", *args])
    last = r.stderr.strip().splitlines()[-1]
    assert r.returncode == 2 and "num_hidden_layers 2 (tiny_arch.text asks 4)" in last, r.stderr
    from labrobfail_vlm.model.tiny import check_built

    check_built(base, {"num_hidden_layers": 2, "hidden_size": 128, "intermediate_size": 256})  # the same size: kept


@pytest.mark.skipif(
    shutil.which("deepspeed", path=os.path.dirname(sys.executable)) is None,
    reason="deepspeed not installed (make install adds it)",
)
def test_deepspeed_two_cpu_ranks_train_save_resume(tiny, small_ds, tmp_path):
    ds_bin = os.path.join(os.path.dirname(sys.executable), "deepspeed")
    out = tmp_path / "ds"
    # the launcher ignores MASTER_PORT and would use 29500 every time: a free port per launch
    common = [
        "train.py",
        "preset=tiny",
        "tuning=hybrid",
        f"model.path={tiny}",
        f"dataset_dir={small_ds}",
        f"output_dir={out}",
        "deepspeed=configs/ds_zero3.json",
        "global_batch=4",
        "per_device_batch=1",
        "tower=scratch",  # a trained tower, so ZeRO-3 must gather the vision and merger weights
        "grounding.weight=0",
        "grounding.pretrain_epochs=0",  # the grounding head runs on one process only
        "save_steps=2",
        "logging_steps=1",
        "wandb.enabled=false",
        "progress=false",
    ]
    launch = [ds_bin, "--num_gpus", "2", "--master_port", str(free_port())]
    r = run([*launch, *common, "max_steps=2"], 900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    # DeepSpeed's CPU all-reduce segments (one per rank, named after the port) are gone from RAM-backed /dev/shm
    assert not list(Path("/dev/shm").glob(f"deepspeed_allreduce_buffer_*_{launch[-1]}_*"))
    from safetensors.torch import load_file

    adapter = load_file(str(out / "checkpoint-2" / "adapter_model.safetensors"))
    vision = load_file(str(out / "checkpoint-2" / "vision_merger.safetensors"))
    assert adapter and all(t.numel() > 0 for t in adapter.values())  # gathered, not empty partitions
    assert any("merger" in k for k in vision) and all(t.numel() > 0 for t in vision.values())
    assert any(float(t.abs().sum()) > 0 for k, t in adapter.items() if "lora_B" in k)  # it trained
    launch[-1] = str(free_port())  # the first run's port may linger in TIME_WAIT
    r = run([*launch, *common, "max_steps=3", "resume=true"], 900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert not list(Path("/dev/shm").glob(f"deepspeed_allreduce_buffer_*_{launch[-1]}_*"))
    summary = json.loads((out / "train_summary.json").read_text())
    assert summary["global_step"] == 3
    assert (out / "final" / "adapter_model.safetensors").is_file()


def test_packed_row_loss_equals_the_six_records_alone(tiny, small_ds):
    """Shared-prefix packing: same per-record losses as unpacked records, the grid encoded once per row."""
    from labrobfail_vlm.model.loading import load_model, load_processor
    from labrobfail_vlm.train.data import Collator
    from labrobfail_vlm.train.packing import TrajectoryDataset, prepare_packed
    from labrobfail_vlm.train.trainer import record_loss

    proc = load_processor(tiny)
    proc.tokenizer.padding_side = "right"
    td = TrajectoryDataset(small_ds, "train")
    items = [td[0], td[1]]
    assert [len(i) for i in items] == [6, 6]
    col = Collator(proc, 1024, {"Q2": 2.0, "Q6": 0.5})
    packed = col(items)
    assert packed["pixel_values"].shape[0] == 2 * 32 * 4  # one image per row: 32 visual tokens x 2x2 patches
    assert packed["record_weight"].numel() == 12
    unpacked = col([r for i in items for r in i])
    model = load_model(tiny).eval()
    with torch.no_grad():
        w, slots, labels = packed.pop("record_weight"), packed.pop("label_slot"), packed.pop("labels")
        got, _ = record_loss(model, prepare_packed(model, packed), labels, w, slots)
        uw, ulabels = unpacked.pop("record_weight"), unpacked.pop("labels")
        want, _ = record_loss(model, unpacked, ulabels, uw)
    assert float(got) == pytest.approx(float(want), rel=1e-5)
    # a branch cannot see another: with the Q1 records weighted 0, rewriting Q1's answer tokens changes nothing
    packed = col(items)
    w, slots, labels = packed.pop("record_weight"), packed.pop("label_slot"), packed.pop("labels")
    w[[0, 6]] = 0.0
    q1 = (slots == 0) | (slots == 6)
    with torch.no_grad():
        before, _ = record_loss(model, prepare_packed(model, dict(packed)), labels, w, slots)
        packed["input_ids"] = packed["input_ids"].masked_fill(q1, int(proc.tokenizer.pad_token_id))
        after, _ = record_loss(model, prepare_packed(model, dict(packed)), labels, w, slots)
    assert float(before) == pytest.approx(float(after), rel=1e-6)


def test_rewording_and_pair_sampler(small_ds):
    from labrobfail_vlm import questions as Q
    from labrobfail_vlm.train.curriculum import PairSampler, Rewording
    from labrobfail_vlm.train.data import VQADataset

    ds = VQADataset(small_ds, "train")
    assert ds.group_of and len(set(ds.group_of.values())) < len(ds.group_of)  # pairs share a group
    # the polarity flips the Q2 answer; other dimensions keep theirs
    q2 = next(ds[i] for i in range(len(ds)) if ds[i]["id"].endswith("_Q2"))
    pos = next(i for i, v in enumerate(Q.VARIANTS["Q2"]) if v.positive)
    neg = next(i for i, v in enumerate(Q.VARIANTS["Q2"]) if not v.positive)
    (qa, aa), (qb, ab) = (
        Q.reask("Q2", q2["question"], q2["answer"], pos),
        Q.reask("Q2", q2["question"], q2["answer"], neg),
    )
    assert Q.VARIANTS["Q2"][pos].text in qa and Q.VARIANTS["Q2"][neg].text in qb and {aa, ab} == {"Yes", "No"}
    rw = Rewording(ds.group_of, pairs=True)
    rw.negative_only = True
    recs = [ds[i] for i in range(len(ds))]
    out = rw(recs)
    assert all(not Q.VARIANTS["Q2"][Q.q2_variant(r["question"])].positive for r in out if r["id"].endswith("_Q2"))
    # twins asked the same wording in one batch
    by = {}
    for r in out:
        by.setdefault((ds.group_of[Q.traj_of(r["id"])], Q.dim_of(r["id"])), set()).add(r["question"])
    assert all(len(v) == 1 for v in by.values())
    # the sampler keeps both records of a (pair, question) unit inside one micro-batch of 4
    order = list(PairSampler([r["id"] for r in ds.records], ds.group_of, 4, seed=1))
    assert sorted(order) == list(range(len(ds)))
    keys = [(ds.group_of[Q.traj_of(ds.records[i]["id"])], Q.dim_of(ds.records[i]["id"])) for i in order]
    where = {}
    for pos_, k in enumerate(keys):
        where.setdefault(k, set()).add(pos_ // 4)
    assert sum(len(v) > 1 for v in where.values()) <= 1  # at most the tail straddles


def test_detect_first_puts_the_loss_on_q2_alone(tiny, small_ds):
    """curriculum.detect_first: while it lasts, the packed batch's record weights are 0 except Q2's."""
    from labrobfail_vlm import questions as Q
    from labrobfail_vlm.model.loading import load_processor
    from labrobfail_vlm.train.curriculum import Rewording
    from labrobfail_vlm.train.data import Collator
    from labrobfail_vlm.train.packing import TrajectoryDataset

    proc = load_processor(tiny)
    proc.tokenizer.padding_side = "right"
    td = TrajectoryDataset(small_ds, "train")
    items = [td[0], td[1]]
    rw = Rewording(td.group_of, pairs=False)
    col = Collator(proc, 1024, {"Q2": 2.0}, rw)
    dims = [Q.dim_of(r["id"]) for i in items for r in i]
    rw.detect_only = True
    w = col(items)["record_weight"].tolist()
    assert [d for d, x in zip(dims, w) if x > 0] == ["Q2", "Q2"] and max(w) == 2.0
    rw.detect_only = False
    assert all(x > 0 for x in col(items)["record_weight"].tolist())
