"""ACT in plain torch: chunking and temporal ensembling on toy cases, a few training steps, checkpoints,
and the train_act.py -> policy=act path on real PyBullet demonstrations."""

import json
import sys

import numpy as np
import pytest
import torch
from conftest import background, run, run_here, serve_policy, supervise_front

from labrobfail_vlm.config import ConfigError
from sim_backends.policies.act.checkpoint import load_checkpoint, save_checkpoint
from sim_backends.policies.act.configuration_act import ACTConfig
from sim_backends.policies.act.data import from_rot6d, rot6d
from sim_backends.policies.act.modeling_act import ACTModel, ChunkRunner, TemporalEnsembler

TOY = dict(
    cameras=["front"],
    image_size=32,
    chunk_size=4,
    backbone_channels=[8, 8, 16, 16],
    dim_model=32,
    n_heads=2,
    dim_feedforward=64,
    n_encoder_layers=1,
    n_decoder_layers=1,
    n_vae_encoder_layers=1,
    latent_dim=4,
    dropout=0.0,
)


def test_temporal_ensembling_weights_the_oldest_chunk_most():
    ens = TemporalEnsembler(chunk_size=3, coeff=0.5)
    assert ens(np.array([[0.0], [1.0], [2.0]]))[0] == 0.0  # t=0: one prediction
    w0, w1 = 1.0, np.exp(-0.5)  # t=1: the chunk from t=0 (oldest, weight exp(0)) and the new one
    assert ens(np.array([[10.0], [11.0], [12.0]]))[0] == pytest.approx((w0 * 1.0 + w1 * 10.0) / (w0 + w1))
    w2 = np.exp(-1.0)
    got = ens(np.array([[20.0], [21.0], [22.0]]))[0]  # t=2: three chunks predict it
    assert got == pytest.approx((w0 * 2.0 + w1 * 11.0 + w2 * 20.0) / (w0 + w1 + w2))
    got = ens(np.array([[30.0], [31.0], [32.0]]))[0]  # t=3: the t=0 chunk has run out (k=3)
    assert got == pytest.approx((1.0 * 12.0 + w1 * 21.0 + w2 * 30.0) / (1.0 + w1 + w2))
    ens.reset()
    assert ens(np.array([[5.0], [6.0], [7.0]]))[0] == 5.0


def test_default_coefficient_is_the_papers():
    assert ACTConfig().temporal_ensemble_coeff == 0.01 and ACTConfig().n_decoder_layers == 1


def test_chunks_run_open_loop_without_ensembling():
    r = ChunkRunner(chunk_size=3)
    seen, queries = [], 0
    for t in range(7):
        chunk = None
        if r.needs_query():
            queries += 1
            chunk = np.arange(3)[:, None] + 10 * t
        seen.append(float(r(chunk)[0]))
    assert queries == 3 and seen == [0, 1, 2, 30, 31, 32, 60]


def test_rotation_6d_round_trip():
    from sim_backends.perturbations.control import so3_exp

    r = so3_exp(np.array([0.3, -1.2, 0.7]))
    assert np.allclose(from_rot6d(rot6d(r)), r, atol=1e-9)
    assert np.allclose(from_rot6d(rot6d(r) + 0.01), from_rot6d(rot6d(r) + 0.01) @ np.eye(3))


def test_act_trains_a_few_steps_and_predicts_chunks(tmp_path):
    torch.manual_seed(0)
    cfg = ACTConfig(
        **TOY,
        stats={"state_mean": [0.0] * 9, "state_std": [1.0] * 9, "action_mean": [0.0] * 10, "action_std": [1.0] * 10},
    )
    model = ACTModel(cfg)
    img, state = torch.rand(4, 1, 3, 32, 32), torch.randn(4, 9)
    actions, pad = torch.randn(4, 4, 10), torch.zeros(4, 4, dtype=torch.bool)
    pad[0, 2:] = True  # the first sample's episode ends after 2 steps
    opt = torch.optim.AdamW(model.parameters(), 1e-3)
    losses = []
    for _ in range(30):
        loss, parts = model.loss(img, state, actions, pad)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(parts["l1"])
    assert losses[-1] < 0.6 * losses[0]
    model.eval()
    assert model.predict(img, state).shape == (4, cfg.chunk_size, 10)
    save_checkpoint(model, cfg, tmp_path / "ck")
    again, cfg2 = load_checkpoint(tmp_path / "ck")
    assert cfg2 == cfg and torch.equal(again.predict(img, state), model.predict(img, state))


def test_augmented_demonstrations_move_the_pictures_not_the_actions():
    from labrobfail_vlm.augment import AugmentConfig
    from sim_backends.policies.act.data import DemoDataset, normalisation

    rng = np.random.default_rng(0)
    images = np.zeros((6, 2, 32, 32, 3), np.uint8)
    images[:, :, 12:20, 12:20] = 200  # a bright square in the middle of both views
    demos = [{"images": images, "state": rng.normal(size=(6, 9)), "action": rng.normal(size=(6, 10))}]
    cfg = ACTConfig(**TOY | {"cameras": ["front", "wrist"]})
    cfg.stats = normalisation(demos)
    aug = AugmentConfig(colour=0.0, shift_px=4.0, scale=0.0)
    plain, a, b = DemoDataset(demos, cfg), DemoDataset(demos, cfg, aug, seed=3), DemoDataset(demos, cfg, aug, seed=3)
    p, x, y = plain[2], a[2], b[2]
    assert torch.equal(x[0], y[0])  # the same seed draws the same pictures
    for k in (1, 2, 3):  # state, action chunk and padding are the demonstration's
        assert torch.equal(x[k], p[k])
    moved = [not torch.equal(x[0][v], p[0][v]) for v in range(2)]
    assert all(moved)
    # each view moved on its own, and only by a shift: the square keeps its size
    centres = [torch.nonzero(x[0][v, 0] > 0.5).float().mean(0) for v in range(2)]
    assert not torch.allclose(centres[0], centres[1])
    assert all(int((x[0][v, 0] > 0.5).sum()) in range(49, 82) for v in range(2))
    assert not torch.equal(a[2][0], x[0])  # a fresh draw per sample


def test_a_chunk_past_the_end_holds_the_last_target_when_asked():
    from sim_backends.policies.act.data import DemoDataset, normalisation

    rng = np.random.default_rng(0)
    demos = [
        {
            "images": np.zeros((6, 1, 32, 32, 3), np.uint8),
            "state": rng.normal(size=(6, 9)),
            "action": rng.normal(size=(6, 10)),
        }
    ]
    cfg = ACTConfig(**TOY)  # chunks of 4
    cfg.stats = normalisation(demos)
    _, _, act, pad, _ = DemoDataset(demos, cfg)[4]
    assert pad.tolist() == [False, False, True, True]  # the reference: past the end is masked out
    _, _, held, pad, _ = DemoDataset(demos, cfg, hold_end=True)[4]
    assert not pad.any() and torch.equal(held, act)  # taught, as the last target held: the plan stands still
    assert torch.equal(held[2], held[1]) and torch.equal(held[3], held[1])


def test_spatial_softmax_finds_a_peak_between_feature_tokens():
    from sim_backends.policies.act.modeling_act import spatial_softmax

    maps = torch.full((1, 2, 8, 8), -50.0)
    maps[0, 0, 2, 5] = 50.0  # row 2, column 5 of 8: pixel centre x = -1 + (2*5+1)/8, y = -1 + (2*2+1)/8
    maps[0, 1, 6, 1] = maps[0, 1, 6, 2] = 50.0  # two equal peaks: their midpoint
    xy = spatial_softmax(maps)[0]  # the x of every map, then the y of every map
    assert torch.allclose(xy, torch.tensor([0.375, -0.5, -0.375, 0.625]), atol=1e-4)


def test_keypoint_tokens_train_and_round_trip(tmp_path):
    torch.manual_seed(0)
    stats = {"state_mean": [0.0] * 9, "state_std": [1.0] * 9, "action_mean": [0.0] * 10, "action_std": [1.0] * 10}
    cfg = ACTConfig(**{**TOY, "cameras": ["front", "wrist"]}, keypoints=6, stats=stats)
    model = ACTModel(cfg)
    img, state = torch.rand(2, 2, 3, 32, 32), torch.randn(2, 9)
    actions, pad = torch.randn(2, 4, 10), torch.zeros(2, 4, dtype=torch.bool)
    loss, _ = model.loss(img, state, actions, pad)
    loss.backward()
    assert model.backbone.kp_maps.weight.grad.abs().sum() > 0  # the keypoints reach the loss
    model.eval()
    save_checkpoint(model, cfg, tmp_path / "ck")
    again, cfg2 = load_checkpoint(tmp_path / "ck")
    assert cfg2.keypoints == 6 and torch.equal(again.predict(img, state), model.predict(img, state))
    with pytest.raises(ValueError, match="act.keypoints"):
        ACTConfig(**TOY, keypoints=-1)


def test_auxiliary_points_are_the_grasp_and_the_tilt_and_the_act_learns_them(tmp_path):
    from sim_backends.policies.act.data import DemoDataset, action_vector, key_points, normalisation
    from sim_backends.policies.act.modeling_act import AUX_SCALE
    from sim_backends.types import matrix_to_quat

    def tilt(a: float) -> tuple:  # about the x axis
        c, s = np.cos(a), np.sin(a)
        return matrix_to_quat(np.array([[1, 0, 0], [0, c, -s], [0, s, c]]))

    # approach open, close at (0.5, 0.1, 0.1), carry, tilt furthest at (0.4, -0.1, 0.3), untilt
    steps = [((0.5, 0.1, 0.3), 0.0, 0), ((0.5, 0.1, 0.1), 0.0, 0), ((0.5, 0.1, 0.1), 0.0, 1)]
    steps += [
        ((0.4, -0.1, 0.3), 0.0, 1),
        ((0.4, -0.1, 0.3), 0.8, 1),
        ((0.4, -0.1, 0.3), 1.6, 1),
        ((0.41, -0.1, 0.3), 0.5, 1),
    ]
    action = np.stack([action_vector(p, tilt(a), g) for p, a, g in steps])
    assert np.allclose(key_points(action), [[0.5, 0.1, 0.1], [0.4, -0.1, 0.3]], atol=1e-6)
    held = action.copy()
    held[:, 9] = 1.0  # a demonstration that starts holding (a regrasp one): its grasp is where it starts
    assert np.allclose(key_points(held)[0], [0.5, 0.1, 0.3], atol=1e-6)

    rng = np.random.default_rng(0)
    state = rng.normal(size=(len(steps), 9)).astype(np.float32)
    state[:, :3] = action[:, :3] + rng.normal(0, 0.005, (len(steps), 3))  # the hand near its targets
    demos = [{"images": rng.integers(0, 255, (len(steps), 1, 32, 32, 3), np.uint8), "state": state, "action": action}]
    cfg = ACTConfig(**TOY, aux_weight=1.0)
    cfg.stats = normalisation(demos)
    *_, points = DemoDataset(demos, cfg)[3]  # relative to the hand at tick 3, in AUX_SCALE metres
    assert torch.allclose(points, torch.from_numpy((key_points(action) - state[3, :3]) / AUX_SCALE), atol=1e-5)

    torch.manual_seed(0)
    model = ACTModel(cfg)
    batch = [torch.stack(x) for x in zip(*[DemoDataset(demos, cfg)[t] for t in range(len(steps))])]
    opt = torch.optim.Adam(model.parameters(), 3e-3)
    first = None
    for _ in range(100):
        loss, parts = model.loss(*batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        first = parts["aux_l1"] if first is None else first
    assert parts["aux_l1"] < 0.5 * first  # the two extra queries learn where the points are
    with pytest.raises(ValueError, match="auxiliary points"):
        model.loss(*batch[:4])
    model.eval()
    save_checkpoint(model, cfg, tmp_path / "ck")
    again, cfg2 = load_checkpoint(tmp_path / "ck")
    assert cfg2.aux_weight == 1.0 and torch.equal(again.predict(batch[0], batch[1]), model.predict(batch[0], batch[1]))
    assert model.predict(batch[0], batch[1]).shape == (len(steps), cfg.chunk_size, 10)  # actions only
    for bad in (-1.0, "abc", None):
        with pytest.raises(ValueError, match="act.aux_weight: must be a number >= 0"):
            ACTConfig(**TOY, aux_weight=bad)


def test_an_act_tilting_in_place_is_not_idle():
    from sim_backends.perturbations.control import so3_exp
    from sim_backends.policies.act.policy import still
    from sim_backends.policies.base import Action
    from sim_backends.types import matrix_to_quat

    up = matrix_to_quat(np.eye(3))
    tilted = matrix_to_quat(so3_exp(np.array([0.15, 0.0, 0.0])))  # one tick of a pour's tilt, the hand in place
    here = Action((0.5, 0.1, 0.2), up, 1)
    assert still(Action((0.5, 0.1, 0.2005), up, 1), here)  # a target that stands still
    assert not still(Action((0.5, 0.1, 0.2), tilted, 1), here)  # tilting in place is work, not idleness
    assert not still(Action((0.5, 0.1, 0.2), up, 0), here)  # so is a release
    assert not still(Action((0.51, 0.1, 0.2), up, 1), here) and not still(here, None)


def test_bad_checkpoints_are_one_line_errors(tmp_path):
    with pytest.raises(ValueError, match="act.checkpoint: no checkpoint directory"):
        load_checkpoint(tmp_path / "none")
    (tmp_path / "ck").mkdir()
    (tmp_path / "ck" / "act.json").write_text(json.dumps(TOY))
    (tmp_path / "ck" / "model.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(ValueError, match="act.checkpoint: cannot load"):
        load_checkpoint(tmp_path / "ck")
    from sim_backends.policies.act.policy import ACTPolicy

    with pytest.raises(ConfigError, match="no checkpoint directory"):
        ACTPolicy(checkpoint=None)


def test_a_correction_gives_the_act_a_new_attempt(tmp_path):
    # an ACT that spent its ticks (most wide-world pours do) could not resume after a final-review correction
    from sim_backends.policies.act.policy import ACTPolicy
    from sim_backends.source import Observation

    torch.manual_seed(0)
    stats = {"state_mean": [0.0] * 9, "state_std": [1.0] * 9, "action_mean": [0.0] * 10, "action_std": [1.0] * 10}
    cfg = ACTConfig(**TOY, stats=stats, temporal_ensemble_coeff=None)
    save_checkpoint(ACTModel(cfg).eval(), cfg, tmp_path / "ck")
    policy = ACTPolicy(checkpoint=str(tmp_path / "ck"), max_ticks=3, idle_stop=0)
    state = {"ee_pos": [0.4, 0.0, 0.3], "ee_quat": [0.0, 0.0, 0.0, 1.0], "width": 0.08, "grip_cmd": 0}
    obs = Observation({"front": np.zeros((32, 32, 3), np.uint8)}, state, 0)
    assert all(policy.act(obs) is not None for _ in range(3)) and policy.act(obs) is None  # the attempt is spent
    policy.after_correction(obs)
    assert all(policy.act(obs) is not None for _ in range(3)) and policy.act(obs) is None  # a new attempt, bounded
    policy.reset(None)
    assert policy.act(obs) is not None and policy.info() == {"ticks": 1}


def test_train_act_then_supervise_and_serve_the_policy(tmp_path):
    """A front + wrist ACT, one plain and one regrasp demonstration (each in its own cache): the wrist view is
    recorded, rendered for the policy in the supervised run (the backend's wrist option), and taken by the
    policy server."""
    out = tmp_path / "act"
    toy = [f"model.{k}={json.dumps(v).replace(' ', '')}" for k, v in TOY.items() if k != "cameras"]
    r = run_here(  # in this process (train_act.py runs as a process in the resume test below)
        [
            sys.executable,
            "scripts/train_act.py",
            "task=pick_place_bottle",
            "demos=1",
            "regrasp_demos=1",
            "train.steps=3",
            "train.batch_size=4",
            "model.cameras=[front,wrist]",
            "model.aux_weight=1.0",
            *toy,
            "progress=false",
            f"out_dir={out}",
        ]
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["steps"] == 3 and summary["demos"]["recorded"] == 1
    assert summary["demos"]["regrasp"]["recorded"] == 1 and (out / "demos_regrasp.npz").is_file()
    assert (out / "final" / "model.safetensors").is_file() and (out / "demos.npz").is_file()
    log = json.loads((out / "train_log.json").read_text())
    assert log["curve"][0]["step"] == 1 and log["demos"]["ticks"] > 10
    with np.load(out / "demos.npz") as z:
        assert z["images"].shape[1] == 2  # front and wrist at every tick
        front, wrist = z["images"][:, 0], z["images"][:, 1]
        assert np.abs(front.astype(int) - wrist.astype(int)).mean() > 5  # two different cameras
    assert "aux_l1" in log["curve"][0]  # the grasp and tilt queries trained
    # where the ACT puts its grasp, against its demonstration's (the regrasp one starts holding: not probed)
    probe = tmp_path / "probe.json"
    cmd = [sys.executable, "scripts/probe_act.py", f"checkpoint={out / 'final'}", f"demos={out / 'demos.npz'}"]
    r = run_here([*cmd, "ahead=[2]", f"out={probe}"])
    assert r.returncode == 0, r.stderr
    res = json.loads(probe.read_text())
    assert res["probed"] == 1 and res["median_error_cm"]["2"]["chunk"] >= 0 and res["median_error_cm"]["2"]["aux"] >= 0
    r = run_here([*cmd, "ahead=[4]"])
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        "error: ahead: a list of ticks from 1 to 3 (the chunk), not [4]"
    ]
    sup = tmp_path / "sup"
    act = ["policy=act", f"act.checkpoint={out / 'final'}", "act.max_ticks=12"]
    r = supervise_front(sup, act, "pick_place_bottle", 1, 48, "backend_kwargs.wrist=true", here=True)
    assert r.returncode == 0, r.stderr
    eps = [json.loads(x) for x in (sup / "log.jsonl").read_text().splitlines() if '"episode"' in x]
    assert len(eps) == 2 and all(e["policy"] == "act" and 0 < e["ticks"] <= 12 for e in eps)
    assert all(e["steps"] <= 12 * (1 + e["interventions"]) for e in eps)  # act.max_ticks per attempt
    # the same checkpoint behind the OpenVLA protocol
    p = serve_policy("policy=act", f"act.checkpoint={out / 'final'}", "port=0")
    try:
        url = p.stdout.readline().split()[-1]
        from sim_backends.policies.openvla_client import OpenVLAClient

        state = {"ee_pos": [0.4, 0.0, 0.3], "ee_quat": [0.0, 0.7071, 0.0, 0.7071], "width": 0.08, "grip_cmd": 0}
        a = OpenVLAClient(url).request(
            {
                "image": np.zeros((48, 48, 3), np.uint8),
                "instruction": "pick",
                "images": {"front": np.zeros((48, 48, 3), np.uint8), "wrist": np.zeros((48, 48, 3), np.uint8)},
                "proprio": np.array([*state["ee_pos"], *state["ee_quat"], 0.08, 0], np.float32),
            }
        )
        assert a.shape == (7,) and np.all(np.isfinite(a))
    finally:
        p.terminate()
        p.wait(timeout=10)


def _clean_and_drifted(task: str, seed: int, **drift: float):
    """A clean demonstration of the task's first scenario and two drifted ones (same seed, same `drift`
    settings of record_demo), on real PyBullet; the two drifted ones must be identical."""
    from labrobfail_vlm.config import load_config
    from sim_backends.policies.act.data import record_demo
    from sim_backends.registry import make_backend
    from sim_backends.supervision.experiment import families, resolve_tasks, scenario_templates

    src = make_backend("pybullet", image_size=32, cameras=["front"], max_distractors=0)
    try:
        fam = resolve_tasks(task, families(load_config("supervise.yaml", []), scenario_templates(src)), [])[0]
        rec = lambda **kw: record_demo(  # noqa: E731
            src, fam.plan, fam.success, fam.scenarios[0], seed, "seen", ["front"], 0.03, 0.15, **kw
        )
        clean, noisy, again = rec(), rec(**drift), rec(**drift)
    finally:
        src.close()
    assert clean is not None and noisy is not None and again is not None
    assert all(np.array_equal(noisy[k], again[k]) for k in ("images", "state", "action"))
    return clean, noisy


def test_a_killed_act_training_resumes_and_ends_as_an_uninterrupted_one(tmp_path):
    """Killed mid-epoch, `resume=true` goes on from the newest checkpoint with the same data order, augmentation
    draws and RNG: the final weights are the uninterrupted run's, bit for bit."""
    import shutil
    import time

    from safetensors.torch import load_file

    from labrobfail_vlm.io import RESUME_TENSORS as OPTIM
    from sim_backends.policies.act.checkpoint import TRAIN_STATE, last_progress

    toy = [f"model.{k}={json.dumps(v).replace(' ', '')}" for k, v in TOY.items()]
    args = [
        *("task=pick_place_bottle", "demos=1", "train.steps=150", "train.batch_size=4", "train.save_every=10"),
        *("train.threads=1", "train.schedule=cosine", "train.augment.enabled=true", "progress=false", *toy),
    ]

    def cmd(out, *extra):
        return [sys.executable, "scripts/train_act.py", *args, f"out_dir={out}", *extra]

    full, cut = tmp_path / "full", tmp_path / "cut"
    r = run_here(cmd(full))  # the uninterrupted run in this process, the killed one a process
    assert r.returncode == 0, r.stderr
    assert "resumed_at_step" not in json.loads(r.stdout.strip().splitlines()[-1])
    steps = sorted(full.glob("checkpoints/step-*"), key=lambda d: int(d.name.split("-")[1]))
    assert [d for d in steps if (d / TRAIN_STATE).is_file()] == [full / "checkpoints" / "step-150"]
    assert all((d / "model.safetensors").is_file() and not (d / OPTIM).exists() for d in steps[:-1])
    cut.mkdir()
    shutil.copy(full / "demos.npz", cut / "demos.npz")  # the same demonstration, not recorded again
    p = background(cmd(cut))

    def reached() -> int:
        last = last_progress(cut / "checkpoints")
        return int(last.name.split("-")[1]) if last else 0

    try:  # killed past its first epoch, where the data order and augmentation draws are no longer the seed's
        while reached() < 60 and p.poll() is None:
            time.sleep(0.02)
    finally:
        p.kill()
        p.wait()
    at = last_progress(cut / "checkpoints")
    assert at is not None and not (cut / "final").exists()
    assert json.loads((at / TRAIN_STATE).read_text())["batch"] < reached(), "killed in the first epoch"
    r = run_here(cmd(cut, "resume=true"))
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["steps"] == 150 and summary["resumed_at_step"] >= int(at.name.split("-")[1])
    a, b = (load_file(str(d / "final" / "model.safetensors")) for d in (full, cut))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    # other settings are not resumed silently, and a run with nothing to resume says so
    for extra, what in ((["train.lr=0.5"], "other settings"), ([f"out_dir={tmp_path / 'none'}"], "no complete")):
        if "out_dir" in extra[0]:
            shutil.copytree(cut, tmp_path / "none", ignore=shutil.ignore_patterns("checkpoints"))
        r = run_here([*cmd(cut, "resume=true"), *extra])  # refusals: in the test's process (resume ran as one)
        assert r.returncode == 2 and "Traceback" not in r.stderr
        assert r.stderr.strip().splitlines()[-1].startswith("error: resume:") and what in r.stderr
    # a clock that runs out before the step count ends the run with a warning that names the step it reached
    short = tmp_path / "short"
    short.mkdir()
    shutil.copy(full / "demos.npz", short / "demos.npz")
    r = run_here(cmd(short, "train.max_minutes=0.000001"))
    assert r.returncode == 0 and json.loads(r.stdout.strip().splitlines()[-1])["steps"] < 150, r.stderr
    assert "warning: train.max_minutes ran out at step" in r.stderr and "of 150" in r.stderr, r.stderr


def test_dart_demonstrations_drift_off_the_line_and_are_labelled_back_onto_it():
    """With `noise`, free moves of the open hand end off their keyframe, the recorded actions stay on the plan's
    line and the grasp is still made where the plan makes it; the same seed gives the same demonstration."""
    clean, noisy = _clean_and_drifted("pick", 3, noise=0.03)

    def close_and_drift(d):
        a, s = d["action"], d["state"]
        t = int(np.argmax(a[:, 9] > 0.5))  # the grasp tick
        return a[t, :3], float(np.abs(s[1 : t + 1, :2] - a[:t, :2]).max())  # where the hand is vs the last action

    (grasp_clean, drift_clean), (grasp_noisy, drift_noisy) = close_and_drift(clean), close_and_drift(noisy)
    assert np.allclose(grasp_clean, grasp_noisy, atol=1e-4)
    assert drift_noisy > drift_clean + 0.008, (drift_clean, drift_noisy)


def test_carrying_drift_comes_back_onto_the_line_before_the_pour():
    """With `carry_noise`, the closed hand drifts off its line while it carries, but the tilt is made exactly
    where a clean demonstration makes it, and the same seed gives the same demonstration."""
    clean, noisy = _clean_and_drifted("pour", 4, carry_noise=0.03)

    def tilt_and_drift(d):
        a, s = d["action"], d["state"]
        carried = a[:, 9] > 0.5
        tilt = int(np.argmax(np.abs(a[:, 3:9] - a[0, 3:9]).sum(1)))  # the tick of the deepest tilt
        off = np.abs(s[1:, :2] - a[:-1, :2]).max(1)  # where the hand is vs the last action
        return s[tilt, :3], float(off[carried[:-1]].max())

    (tilt_clean, drift_clean), (tilt_noisy, drift_noisy) = tilt_and_drift(clean), tilt_and_drift(noisy)
    assert np.allclose(tilt_clean, tilt_noisy, atol=5e-3), (tilt_clean, tilt_noisy)
    assert drift_noisy > drift_clean + 0.008, (drift_clean, drift_noisy)


def test_regrasp_demonstrations_start_from_a_corrected_grasp_and_lift():
    """With `miss`, the grasp closes beside the vessel, the P4 correction regrasps it unrecorded, and the
    demonstration starts with the vessel held at grasp height (fingers on it, not shut) and lifts it; a plain
    demonstration starts with the hand open, far above; the same seed gives the same demonstration."""
    plain, regrasp = _clean_and_drifted("pour", 4, miss=0.08)
    s0, r0, b0 = plain["state"][0], regrasp["state"][0], regrasp["action"][0]
    assert s0[8] == 0 and s0[2] > 0.2  # grip_cmd open, the hand at its start pose
    assert r0[8] == 1 and r0[7] > 0.03 and r0[2] < 0.08, r0  # closed on the vessel, at grasp height
    assert b0[9] > 0.5 and b0[2] > r0[2]  # the first recorded action keeps holding and rises
    assert len(regrasp["action"]) < len(plain["action"])  # the approach and grasp are not in it


@pytest.mark.parametrize(
    "arg",
    [
        "noise=-0.01",
        "carry_noise=far",
        "miss=-0.01",
        "regrasp_demos=-1",
        "miss=0.01 regrasp_demos=2",
        "train.schedule=linear",
        "train.warmup=-5",
        "train.augment.shift_px=wide train.augment.enabled=true",
    ],
)
def test_bad_drift_or_schedule_is_a_one_line_error(arg, tmp_path):
    argv = [sys.executable, "scripts/train_act.py", *arg.split(), f"out_dir={tmp_path / 'act'}"]
    r = run(argv, 120) if arg == "noise=-0.01" else run_here(argv)  # the first case as a real process
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith(f"error: {arg.split('=')[0]}:"), r.stderr
    assert not (tmp_path / "act").exists()
