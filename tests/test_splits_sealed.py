"""Splits that cannot leak: every variant draws its own episodes, the sealed catalogue and scene family lie outside
every family that training, tower pretraining or augmentation draws from, intervals resample whole pairs, and every
bench run on a sealed split is counted."""

from __future__ import annotations

import colorsys
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from labrobfail_vlm.taxonomy import SCENE_VARIANTS, SEALED_SPLITS

# Two short scenarios, one tiny view: the episodes are real PyBullet runs, only small.
GEN = ["image_size=32", "cameras=[front]", "render_frames=4", "scenarios=[press_button_red,pick_place_beaker_small]"]


def _generate(out: Path, *extra: str) -> list[dict]:
    from sim_backends.generate import generate, load_config

    generate(load_config([f"out_dir={out}", "num_episodes=4", "seed=3", "progress=false", *GEN, *extra]))
    cols = ["variant", "role", "scenario", "seed", "task_meta", "perturbation"]
    return [r for f in sorted(out.glob("shard-*.parquet")) for r in pq.read_table(f, columns=cols).to_pylist()]


def _initial_state(row: dict) -> str:
    """Where every object and place of the task stood when the episode began (the task metadata's homes)."""
    meta = json.loads(row["task_meta"])
    return json.dumps([{k: o["home"] for k, o in sorted(meta["objects"].items())}, meta["places"]], sort_keys=True)


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, list[dict]]:
    root = tmp_path_factory.mktemp("variants")
    out = {v: _generate(root / v, f"variant={v}") for v in SCENE_VARIANTS}
    out["replay_val_object"] = _generate(root / "replay", "variant=val_object", "replay_seen=true")
    return out


def test_no_two_variants_share_a_seed_an_initial_state_or_an_injection(runs):
    """The same seed and pair numbers in every variant: each draws episodes of its own (the bug this replaces:
    unseen pair j was seen pair j in new colours)."""
    own = {v: rows for v, rows in runs.items() if v in SCENE_VARIANTS}
    assert all(len(rows) == 4 for rows in own.values())
    for key in ("seed", "initial state", "injection"):
        owners: dict[str, str] = {}
        for v, rows in own.items():
            for r in rows:
                if key == "injection" and r["role"] != "injected":
                    continue
                value = {"seed": r["seed"], "initial state": _initial_state(r), "injection": r["perturbation"]}[key]
                assert owners.setdefault(str(value), v) == v, f"{key} of {v} is also {owners[str(value)]}'s"


def test_a_replay_is_the_seen_episodes_under_its_own_name(runs):
    """`replay_seen=true` is the one way to see a seen episode in held-out colours, and it is never called val."""
    seen, replay = runs["seen"], runs["replay_val_object"]
    assert {r["variant"] for r in replay} == {"replay_val_object"}
    assert [(r["scenario"], r["seed"], r["perturbation"]) for r in replay] == [
        (r["scenario"], r["seed"], r["perturbation"]) for r in seen
    ]


def test_pair_seeds_differ_across_variants_and_seen_keeps_its_seeds():
    from sim_backends.generate import pair_seed, scenario_order

    seeds = {v: {pair_seed(0, j, d, v) for j in range(2000) for d in (0, 1)} for v in SCENE_VARIANTS}
    assert all(len(s) == 4000 for s in seeds.values())
    for i, a in enumerate(SCENE_VARIANTS):
        for b in SCENE_VARIANTS[i + 1 :]:
            assert not seeds[a] & seeds[b], (a, b)
    # seen's seeds and order are those of runs made before variants had their own: the same seed, the same data
    legacy = np.random.SeedSequence([0, 7]).generate_state(1)[0], np.random.SeedSequence([0, 7, 2]).generate_state(1)[0]
    assert (pair_seed(0, 7), pair_seed(0, 7, 2)) == tuple(int(x) for x in legacy)
    names = [f"s{i}" for i in range(12)]
    assert scenario_order(names, 0, 24) != scenario_order(names, 0, 24, variant="val_both")


def test_replay_and_renamed_variants_are_refused_in_one_line(tmp_path):
    from labrobfail_vlm.config import ConfigError
    from sim_backends.generate import generate, load_config

    for extra, msg in (
        (["variant=unseen_both"], "variant: 'unseen_both' was renamed; use val_both"),
        (["replay_seen=true"], "replay_seen: replays the seen episodes under a held-out variant's appearance"),
    ):
        with pytest.raises(ConfigError, match=msg):
            generate(load_config([f"out_dir={tmp_path / 'x'}", "num_episodes=2", *extra]))


def _hsv(rgba) -> tuple[float, float, float]:
    return colorsys.rgb_to_hsv(*rgba[:3])


def test_the_sealed_scene_family_is_outside_every_other_family():
    """Sampled, not read from the table: the sealed benches are more saturated and the sealed floors more coloured
    than anything the seen, val or randomised (tower pretraining) family draws, with texture kinds of their own."""
    from sim_backends.pybullet import scene

    def draws(variant: str, family: str | None = None) -> list[dict]:
        return [scene.draw_appearance(variant, np.random.default_rng(i), family) for i in range(1500)]

    others = {"seen": draws("seen"), "val": draws("val_scene"), "randomised": draws("seen", "randomised")}
    sealed = draws("test_scene")
    assert draws("test_both")[:50] == sealed[:50] and draws("test_object")[:50] == others["seen"][:50]
    for part in ("bench", "floor"):
        low = min(_hsv(a[part])[1] for a in sealed)
        for name, app in others.items():
            assert max(_hsv(a[part])[1] for a in app) < low, f"{part} saturation of {name} reaches the sealed range"
    kinds = {a["texture"] for a in sealed}
    assert kinds == {"dots", "rings"}
    for name, app in others.items():
        assert not kinds & {a["texture"] for a in app}, name


def _patches(colours: list[list[float]], rng: np.random.Generator) -> np.ndarray:
    """A 96x96 picture of 16 patches, each one of `colours` under a lighting factor in [0.45, 1] (shade and light on
    a bench or floor scale its RGB), as a rendered view of that surface shows it."""
    pick = rng.choice(len(colours), size=16)
    cells = [np.array(colours[i][:3]) * rng.uniform(0.45, 1.0) * 255 for i in pick]
    img = np.stack([np.stack([cells[4 * (r // 24) + c // 24] for c in range(96)]) for r in range(96)])
    return np.round(img).astype(np.uint8)


def _trained_augmentations(tmp_path: Path) -> dict:
    """Every augmentation setting a model of the page trains on: each stage of `make tower` (configs/tower.yaml with
    the stage's command line, read from a dry run) and the VQA trainer's (configs/train.yaml)."""
    from omegaconf import OmegaConf

    from labrobfail_vlm.augment import AugmentConfig

    plan = _make_dry("tower", f"T={tmp_path}")
    assert plan.returncode == 0, plan.stderr
    root = Path(__file__).resolve().parents[1]
    text = plan.stdout.replace("\\\n", "")  # a command continued over lines is one command
    stages = [line.split() for line in text.splitlines() if "labrobfail-pretrain-tower" in line]
    assert len(stages) == 3
    out = {}
    for k, words in enumerate(stages):
        cfg = OmegaConf.merge(
            OmegaConf.load(root / "configs" / "tower.yaml"),
            OmegaConf.from_dotlist([w for w in words if w.startswith("augment.")]),
        )
        out[f"tower stage {k + 1}"] = AugmentConfig.from_section(cfg.augment)
    out["train.yaml"] = AugmentConfig.from_section(OmegaConf.load(root / "configs" / "train.yaml").augment)
    return out


def test_no_augmentation_a_model_trains_on_brings_a_family_into_the_sealed_saturation(tmp_path):
    """Whole-picture colour changes (brightness, contrast, saturation, any hue) act on every pixel: a contrast or
    saturation gain turns a randomised bench (saturation up to 0.7) into a sealed one (0.75 and more), and a grey
    floor into a coloured one. Every setting that trains a model (the tower's three stages, the VQA trainer) keeps
    each pixel's saturation at most what it was rendered with, so pictures of every other family's drawn colours
    under light (each under the sealed range before), augmented as trained, stay under the sealed family's bench and
    floor saturation; the setting of the tower shipped until 6 Dec did not. (Rendering itself can give a very dark
    pixel any saturation by rounding, in every family: the families are told apart by their drawn colours.)"""
    from labrobfail_vlm.augment import Augment, AugmentConfig, hsv_saturation
    from sim_backends.pybullet import scene

    def colours(variant: str, part: str, family: str | None = None) -> list[list[float]]:
        return [scene.draw_appearance(variant, np.random.default_rng(i), family)[part] for i in range(300)]

    def reached(cfg: AugmentConfig, part: str, low: float) -> float:
        """The highest saturation of an augmented picture of another family's `part` (each below `low` before)."""
        rng, top = np.random.default_rng(0), 0.0
        for name, fam in (("seen", None), ("val_scene", None), ("seen", "randomised")):
            cols = colours(name, part, fam)
            for _ in range(40):
                img = _patches(cols, rng)
                assert hsv_saturation(img).max() < low
                top = max(top, float(hsv_saturation(Augment.draw(cfg, 1, rng).image(img, 0)).max()))
        return top

    fam = scene.SCENE_FAMILIES["sealed"]
    sealed = {"bench": fam["bench_sat"][0], "floor": fam["floor_sat"][0]}
    assert all(min(_hsv(c)[1] for c in colours("test_scene", part)) >= low for part, low in sealed.items())
    for name, cfg in _trained_augmentations(tmp_path).items():
        assert cfg.raise_saturation is False, name
        for part, low in sealed.items():
            assert reached(cfg, part, low) < low, f"{name}: an augmented {part} reaches the sealed saturation"
    before = AugmentConfig(colour=0.75, hue=0.5)  # stages two and three of the tower shipped until 6 Dec (its card)
    assert reached(before, "bench", sealed["bench"]) >= sealed["bench"]


def _make_dry(target: str, *settings: str, checks: bool = False) -> subprocess.CompletedProcess:
    """`make -n target settings...` in the checkout: what make would run, read by make itself (nothing is built or
    installed); `checks`: run it for real with the install taken as done, for a target whose first lines refuse
    bad settings (a test that they do, before anything runs)."""
    make = shutil.which("make")
    if make is None:
        pytest.skip("make is not installed")
    # the suite itself runs under make test: its MAKEFLAGS and MAKELEVEL would make this one a sub-make
    # and a model named in the environment would stand in for the Makefile's defaults the tests read
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL", "VLM", "MONITOR_VLM")}
    how = ["-s", "-o", ".venv/.installed-stamp"] if checks else ["-n"]
    cmd = [make, *how, "--no-print-directory", target, *settings]
    root = Path(__file__).resolve().parents[1]
    return subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=60)


def test_make_reproduce_resumes_training_only_where_a_checkpoint_was_left(tmp_path):
    """`make reproduce` (a dry run): a fresh folder trains from scratch (resume=true would refuse it), a folder an
    interrupted run left a checkpoint in resumes (before, the recipe's training restarted from step 0)."""

    def train_line() -> str:
        plan = _make_dry("reproduce", f"R={tmp_path}")
        assert plan.returncode == 0, plan.stderr
        (line,) = [x for x in plan.stdout.splitlines() if "labrobfail-train" in x]
        return line.rstrip()

    assert train_line().endswith(f"output_dir={tmp_path}/train") and "resume=true" not in train_line()
    (tmp_path / "train" / "checkpoint-1600").mkdir(parents=True)
    assert train_line().endswith("resume=true")


def test_a_tower_candidate_trains_the_recipe_on_its_data_and_benches_validation_only(tmp_path):
    """`make reproduce-tower` (a dry run): the recipe's training on make reproduce's dataset with the other tower, no
    episode generated, and benches on seen val and the three validation splits only (never seen test or sealed)."""
    got = _make_dry("reproduce-tower", f"R={tmp_path}", "TOWER_DIR=elsewhere/t")
    assert got.returncode == 0, got.stderr
    text = got.stdout.replace("\\\n", "").replace(str(tmp_path), "R")
    assert "labrobfail-generate" not in text
    (train,) = [line for line in text.splitlines() if "labrobfail-train" in line]
    assert "tower=elsewhere/t" in train.split() and "dataset_dir=R/dataset" in train.split()
    assert "output_dir=R/rows/tower_new" in train.split()
    benched = re.findall(r"for s in ([\w ]+); do", text)
    assert benched == ["val val_object val_scene val_both", "val"]
    got = _make_dry("reproduce-tower", f"R={tmp_path}", "TOWER_DIR=elsewhere/t", "TOWER_ROW=tower_c")
    assert f"output_dir={tmp_path}/rows/tower_c" in got.stdout.replace("\\\n", "").split()  # a second candidate


def test_the_16_keyframe_candidate_draws_the_recipes_pairs_and_never_a_sealed_split(tmp_path):
    """`make reproduce-grid16` (a dry run of `val_lever`, the Makefile's validation-only lever): every episode set it
    generates is one of `make reproduce`'s (the same seed, variant, count and first pair; only the rendering differs,
    set last so it wins), it builds 16-keyframe grids of the front and side views, and it neither generates nor benches
    a sealed (test_*) split or seen test."""

    def plan(target: str) -> list[str]:
        got = _make_dry(target, f"R={tmp_path}")
        assert got.returncode == 0, got.stderr
        text = got.stdout.replace("\\\n", "").replace(str(tmp_path), "R")  # pytest's folder names hold "test"
        text = re.sub(r"\$\(\((.*?)\)\)", lambda m: m.group(0).replace(" ", ""), text)  # first_pair=$((4000/2))
        return [line for line in text.splitlines() if line.strip()]

    def episodes(lines: list[str]) -> list[tuple[str, ...]]:
        """Each generate command's settings that choose episodes (rendering and the folder left out)."""
        out = []
        for line in lines:
            words = line.split()
            if not any(w.endswith("labrobfail-generate") for w in words):
                continue
            drop = ("render_frames=", "backend_kwargs.wrist=", "backend_kwargs.broken_glass=", "out_dir=", "progress=")
            out.append(tuple(sorted(w for w in words if "=" in w and not w.startswith(drop))))
        return out

    lever, recipe = plan("reproduce-grid16"), plan("reproduce")
    assert episodes(lever) and set(episodes(lever)) <= set(episodes(recipe))
    gen = [line for line in lever if "labrobfail-generate" in line]
    assert all(line.split("render_frames=")[-1].startswith("16") for line in gen)
    assert all(line.split("backend_kwargs.wrist=")[-1].startswith("false") for line in gen)
    (build,) = [line for line in lever if "labrobfail-build-dataset" in line]
    assert "grid.max_frames=16" in build and "'views=[front,side]'" in build and "test_" not in build
    benches = [line for line in lever if "labrobfail-evaluate" in line]
    assert benches and not any("test" in line.split("split=")[0] for line in benches)
    assert all("for s in val" in line for line in benches)
    assert not any("test" in line for line in gen)


def test_extra_training_episodes_are_drawn_in_seen_or_randomised_scenes_only(tmp_path):
    """`make reproduce-more`'s MORE_FAMILY (a dry run): the randomised family reaches the generator and names its own
    shards, dataset and row; a val or sealed family (or none) is refused in one line before any step."""

    def dry(family: str) -> subprocess.CompletedProcess:
        return _make_dry("reproduce-more", f"R={tmp_path}", f"MORE_FAMILY={family}")

    plan = dry("randomised")
    assert plan.returncode == 0, plan.stderr
    assert "backend_kwargs.scene_family=randomised" in plan.stdout and f"output_dir={tmp_path}/rows/rand" in plan.stdout
    seen = dry("seen")
    assert seen.returncode == 0 and "scene_family" not in seen.stdout and f"{tmp_path}/rows/more" in seen.stdout
    # the randomised row is benched again at the cut chosen on its own seen-val bench, which it benches first
    opval = [line for line in plan.stdout.splitlines() if "threshold=val" in line]
    assert len(opval) == 1 and "test_both" in opval[0] and " val " not in opval[0]
    assert "threshold=val" not in seen.stdout
    assert plan.stdout.index("for s in val test") < plan.stdout.index(opval[0])
    for family in ("val", "sealed", "", "seen val"):
        got = dry(family)
        assert got.returncode != 0 and not got.stdout, family
        (line,) = got.stderr.strip().splitlines()
        assert "MORE_FAMILY is seen or randomised" in line and f"'{family}'" in line


def test_the_randomised_rows_tuned_stages_train_on_its_data_and_report_at_its_cut(tmp_path):
    """`make reproduce-tuned TUNED_ROW=rand` (a dry run): the stages start from the randomised row and train on the
    data it trained on (dataset_rand added), into rows/rand_tuned; `make report-tuned TUNED_ROW=rand` benches the
    sealed splits once at 0.5 and once at the cut chosen on val, then writes the rows section. `TUNED_ROW=rand2` is one
    more stage from that row with new randomised episodes, `rand3` one more from rand2's with newer ones. Without
    TUNED_ROW the stages are make reproduce's; any other row is refused in one line."""
    plan = _make_dry("reproduce-tuned", f"R={tmp_path}", "TUNED_ROW=rand", "TUNED_STAGES=1")
    assert plan.returncode == 0, plan.stderr
    train = next(line for line in plan.stdout.splitlines() if "extra_train=" in line)
    assert f"'extra_train=[{tmp_path}/dataset_rand]'" in train
    assert "labrobfail-generate" not in plan.stdout and "dataset_rand2" not in plan.stdout
    assert f"output_dir={tmp_path}/rows/rand_tuned/stage" in train
    assert f"prev={tmp_path}/rows/rand/final" in plan.stdout and "lr.vision=3e-5" in plan.stdout
    report = _make_dry("report-tuned", f"R={tmp_path}", "TUNED_ROW=rand").stdout.splitlines()
    (opval,) = [line for line in report if "threshold=val" in line]
    assert "eval_${s}_opval/results.json" in opval and "test_both" in opval and " val " not in opval
    assert "'sections=[rows]'" in report[-1] and f"model={tmp_path}/rows/rand_tuned/" in opval
    main = _make_dry("reproduce-tuned", f"R={tmp_path}").stdout
    assert "extra_train" not in main and f"output_dir={tmp_path}/tuned/stage" in main
    # rand2: one stage from the two-stage row, on its data plus new randomised pairs numbered after rand's
    more = _make_dry("reproduce-tuned", f"R={tmp_path}", "TUNED_ROW=rand2", "TUNED_STAGES=2").stdout
    gen = next(line for line in more.splitlines() if "labrobfail-generate" in line)
    assert "backend_kwargs.scene_family=randomised" in gen and "num_episodes=4000" in gen
    # the first pair after rand's last, read from rand's own run record when the step runs
    first = gen.split("first_pair=$(")[1].split(") out_dir=")[0]
    assert f"{tmp_path}/shards/rand/run.json" in first and "r['first_pair'] + r['num_episodes'] // 2" in first
    assert f"test -f {tmp_path}/dataset_rand2/stats.json ||" in gen
    assert gen.rstrip().endswith("'views=[front,side]' 'ratios=[1,0,0]' progress=false; } || exit 1")
    train = next(line for line in more.splitlines() if "extra_train=" in line)
    assert f"'extra_train=[{tmp_path}/dataset_rand,{tmp_path}/dataset_rand2]'" in train
    assert f"prev={tmp_path}/rows/rand_tuned/final" in more and "$(seq 1 1)" in more
    assert f"ln -sfnT stage1/final {tmp_path}/rows/rand2_tuned/final" in more
    assert f"run make reproduce-tuned TUNED_ROW=rand first (no {tmp_path}/rows/rand_tuned/final)" in more
    report = _make_dry("report-tuned", f"R={tmp_path}", "TUNED_ROW=rand2").stdout
    assert f"model={tmp_path}/rows/rand2_tuned/" in report and "threshold=val" not in report  # its cut not adopted
    assert "test_both" in report and report.rstrip().endswith("'sections=[rows]'")
    # rand3: one stage from rand2's row on the dataset plus new pairs after rand2's only, reported at its cut too
    more = _make_dry("reproduce-tuned", f"R={tmp_path}", "TUNED_ROW=rand3").stdout
    gen = next(line for line in more.splitlines() if "labrobfail-generate" in line)
    assert f"{tmp_path}/shards/rand2/run.json" in gen and f"out_dir={tmp_path}/shards/rand3 " in gen
    # without the pairs it follows, one line saying which step makes them (not a Python traceback)
    assert f"test -f {tmp_path}/shards/rand2/run.json || {{ echo" in gen
    assert '(the pairs these follow: run make reproduce-tuned TUNED_ROW=rand2 first)" >&2; exit 2' in gen
    assert f"'shards=[{tmp_path}/shards/rand3]' out_dir={tmp_path}/dataset_rand3 " in gen
    assert f"'extra_train=[{tmp_path}/dataset_rand3]'" in more and f"prev={tmp_path}/rows/rand2_tuned/final" in more
    report = _make_dry("report-tuned", f"R={tmp_path}", "TUNED_ROW=rand3").stdout
    (opval,) = [line for line in report.splitlines() if "threshold=val" in line]
    assert f"model={tmp_path}/rows/rand3_tuned/" in opval and "test_both" in opval
    for row in ("more", "rand more", "val_both", "rand9"):
        got = _make_dry("reproduce-tuned", f"R={tmp_path}", f"TUNED_ROW={row}")
        assert got.returncode != 0 and not got.stdout, row
        (line,) = got.stderr.strip().splitlines()
        assert "TUNED_ROW is rand, rand2 or rand3" in line and f"'{row}'" in line


def test_supervised_trials_draw_what_the_recipes_grids_draw(tmp_path):
    """`make recovery` (a dry run): every drawing option the recipe's generation sets beside the scene (broken glass,
    the button lamp) reaches each supervised run, scripted and ACT, and the pour ACT's rollouts that teach its
    supervisor, so the supervisor never sees grids unlike those it was taught on."""
    vlm, act = tmp_path / "vlm", tmp_path / "act" / "pour_hold" / "final"  # the pour cell's rollouts need both
    for folder, name in ((vlm, "labrobfail.json"), (act, "model.safetensors")):
        folder.mkdir(parents=True)
        (folder / name).write_text("{}")
    plan = _make_dry("recovery", f"R={tmp_path}", f"VLM={vlm}")
    assert plan.returncode == 0, plan.stderr
    text = plan.stdout.replace("\\\n", "").replace(";", "\n")
    gen = _make_dry("reproduce", f"R={tmp_path}").stdout.replace("\\\n", "")
    gen_line = next(line for line in gen.splitlines() if "labrobfail-generate" in line)
    # every backend option but the views and the physics preset (supervised runs take the same preset as the
    # backend's default: naming it there would change the identity a cached run resumes by)
    looks = {w for w in gen_line.split() if w.startswith("backend_kwargs.") and not ("wrist" in w or "physics" in w)}
    assert looks == {"backend_kwargs.broken_glass=true", "backend_kwargs.button_lamp=true"}
    runs = [line for line in text.splitlines() if "labrobfail-supervise" in line]
    assert len(runs) == 5 and sum("policy=act" in r for r in runs) == 4 and "supervisor=none" in "".join(runs)
    for run in runs:
        assert looks <= set(run.split()), run


def test_recovery_monitor_asks_the_model_taught_prefix_grids_unless_told_otherwise(tmp_path):
    """`make recovery-monitor` (a dry run): the page's table is the model of make reproduce-online diagnosing what
    the monitor flags, so that is its default; VLM= or MONITOR_VLM= on the command line names another."""
    for made in ("dataset/stats.json", "robot_online_val_both/monitor/monitor.json"):  # the monitor after its data
        (tmp_path / made).parent.mkdir(parents=True)
        (tmp_path / made).write_text("{}")

    def model(*settings: str) -> str:
        plan = _make_dry("recovery-monitor", f"R={tmp_path}", *settings)
        assert plan.returncode == 0, plan.stderr
        run = next(w for w in plan.stdout.split() if w.startswith("vlm.model="))
        used = run.split("=", 1)[1]
        assert f'test -d "{used}"' in plan.stdout  # the model checked is the model run
        return used

    assert model() == f"{tmp_path}/online/final"
    assert model(f"VLM={tmp_path}/other") == f"{tmp_path}/other"
    assert model(f"MONITOR_VLM={tmp_path}/third") == f"{tmp_path}/third"


def test_the_act_alarm_cell_is_calibrated_on_that_acts_own_rollouts_apart_from_its_trials(tmp_path):
    """`make recovery-act-alarm` (a dry run, pick and place): the cell's model is taught one set of the ACT's own
    rollouts and its alarm calibrated on another (half calibration, half a held-out check); the cell reads that
    bench's online.json; the rollout runs are apart from each other, from the cell's trials (ACT_ALARM_SEED), from
    the development block and from the other task's runs, and all are the cell's own ACT; pour is refused."""
    model = tmp_path / "online" / "final"
    model.mkdir(parents=True)
    (tmp_path / "dataset_online").mkdir()
    (tmp_path / "dataset_online" / "stats.json").write_text("{}")

    def word(run: str, key: str) -> str:
        words = [w.strip("'") for w in run.split()]  # a list is quoted for the shell
        return [w.split("=", 1)[1] for w in words if w.startswith(key + "=")][-1]  # the last one wins

    spans: list[tuple[int, int]] = []  # every rollout run's seeds, both tasks
    cal_seeds = {"pick": ("40000", "40300"), "place": tuple(str(42000 + 300 * i) for i in range(6))}
    for task, runs_made, block in (("pick", 4, 25000), ("place", 8, 26000)):
        plan = _make_dry("recovery-act-alarm", f"R={tmp_path}", "ACT_ALARM_ROLLOUTS=300", f"ACT_ALARM_TASK={task}")
        assert plan.returncode == 0, plan.stderr
        lines = plan.stdout.replace("\\\n", "").splitlines()
        runs = [line for line in lines if "labrobfail-" in line]
        rollouts = next(r for r in runs if "supervisor=none" in r)
        calib, taught = (next(r for r in runs if "build-dataset" in r and k in r) for k in ("[0,0.5,0.5]", "[1,0,0]"))
        stage = next(r for r in runs if "labrobfail-train" in r)
        bench = next(r for r in runs if "mode=online" in r)
        cell = next(r for r in runs if "supervisor=vlm" in r)
        ft = word(stage, "output_dir")
        assert f"model.path={model}" in stage and "prefix.cuts=1" in taught and "|| exit 1" in rollouts
        assert ft == f"{tmp_path}/actft_{task}" and word(cell, "task") == task
        assert word(stage, "extra_train") == f"[{word(taught, 'out_dir')}]"
        assert bench.startswith(f"test -f {word(bench, 'out_dir')}/online.json ||")  # made once
        assert word(bench, "model") == f"{ft}/final" and word(bench, "dataset_dir") == word(calib, "out_dir")
        assert "split=test" in bench and "calibration=val" in bench
        assert (
            word(cell, "vlm.model") == f"{ft}/final"
            and word(cell, "vlm.alarm") == f"{word(bench, 'out_dir')}/online.json"
        )
        assert word(cell, "seed") == str(block) and word(cell, "out_dir") == f"{tmp_path}/recovery/act_alarm/{task}"
        page = next(i for i, line in enumerate(lines) if "write_results.py" in line)
        assert page > lines.index(cell)  # the page spliced after the cell has run
        calls = [r for r in rollouts.replace(";", "\n").splitlines() if "supervisor=none" in r]
        assert len(calls) == runs_made
        for r in calls:
            assert word(r, "act.checkpoint") == word(cell, "act.checkpoint") and word(r, "task") == task
            shards = f"{word(r, 'out_dir')}/shards/none"
            calibrating = word(r, "seed") in cal_seeds[task]  # the task's calibration runs, the others teach
            assert (shards in calib) == calibrating and (shards in taught) != calibrating
            spans.append((int(word(r, "seed")), int(word(r, "seed")) + int(word(r, "trials"))))
        # a run off the reporting block (the development block) writes elsewhere and leaves the page alone
        dev = f"{tmp_path}/dev_{task}"
        off_block = (f"ACT_ALARM_TASK={task}", "ACT_ALARM_SEED=10000", f"ACT_ALARM_OUT={dev}")
        plan = _make_dry("recovery-act-alarm", f"R={tmp_path}", *off_block)
        assert plan.returncode == 0 and f"seed=10000 out_dir={dev}" in plan.stdout.replace("\\\n", "")
        assert "write_results.py" not in plan.stdout
        # and gets past every check, run for real: it stops at the ACT's training (PY=false), not at a refusal
        plan = _make_dry("recovery-act-alarm", f"R={tmp_path}", "PY=false", "BIN=/nonexistent", *off_block, checks=True)
        assert plan.returncode != 0 and "recovery-act-alarm: " not in plan.stderr and "Error" in plan.stderr
    spans.sort()
    assert all(a[1] <= b[0] for a, b in zip(spans, spans[1:]))  # no seed in two runs, of either task
    for first, end in spans:  # nor in the development block or any reporting block
        assert not any(first < b_end and b < end for b, b_end in ((10000, 10100), (20000, 26100)))
    refusals = [  # each refused in its own words before anything runs (PY and BIN name nothing that could run)
        ("ACT_ALARM_TASK is pick or place, not 'pour'", ["ACT_ALARM_TASK=pour"]),
        ("ACT_ALARM_TASK is pick or place, not 'pour'", ["ACT_ALARM_TASK=pour", "ACT_ALARM_CAL_pour=47000"]),
        ("ACT_ALARM_ROLLOUTS is a count from 1 to 300", ["ACT_ALARM_ROLLOUTS=301"]),
        ("ACT_ALARM_ROLLOUTS is a count from 1 to 300", ["ACT_ALARM_ROLLOUTS=0"]),
        ("ACT_ALARM_SEED 10000 into ACT_ALARM_OUT", ["ACT_ALARM_TASK=place", "ACT_ALARM_SEED=10000"]),
        # the page's folder however it is written, or another task's folder the page also reads
        (
            "ACT_ALARM_SEED 10000 into ACT_ALARM_OUT",
            ["ACT_ALARM_TASK=place", "ACT_ALARM_SEED=10000", f"ACT_ALARM_OUT={tmp_path}/recovery/act_alarm/place/"],
        ),
        (
            "ACT_ALARM_SEED 26000 into ACT_ALARM_OUT",
            ["ACT_ALARM_TASK=place", f"ACT_ALARM_OUT={tmp_path}/recovery/act_alarm/pour"],
        ),
    ]
    for words, settings in refusals:
        plan = _make_dry("recovery-act-alarm", f"R={tmp_path}", "PY=false", "BIN=/nonexistent", *settings, checks=True)
        assert plan.returncode == 2 and plan.stderr.count("\n") == 2 and f"recovery-act-alarm: {words}" in plan.stderr


def test_the_sealed_catalogue_has_shapes_sizes_and_colours_of_its_own():
    from sim_backends.pybullet.scene import SEALED_OBJECTS, SEEN_OBJECTS, VAL_OBJECTS

    def shape(o: dict) -> tuple:
        return (o["kind"], o.get("sides"), o.get("neck_radius", 0) > 0)

    def size(o: dict) -> tuple:
        return (o["radius"], o["height"]) if o["kind"] == "vessel" else (o["length"], o["radius"])

    trained = list(SEEN_OBJECTS.values()) + list(VAL_OBJECTS.values())
    assert set(SEALED_OBJECTS) == set(SEEN_OBJECTS)  # the same tasks, other glassware
    for name, o in SEALED_OBJECTS.items():
        if o["kind"] == "vessel":
            assert shape(o) not in {shape(t) for t in trained}, name
        assert size(o) not in {size(t) for t in trained}, name
        nearest = min(float(np.linalg.norm(np.subtract(o["rgba"][:3], t["rgba"][:3]))) for t in trained)
        assert nearest > 0.2, f"{name}'s colour is {nearest:.2f} from a trained object's"
    # glassware drawn in any colour for the tower (object_colours) stays less saturated than every sealed object
    import colorsys

    from sim_backends.pybullet.scene import OBJECT_COLOURS

    sealed = min(colorsys.rgb_to_hsv(*o["rgba"][:3])[1] for o in SEALED_OBJECTS.values())
    assert all(f["sat"][1] < sealed - 0.02 for f in OBJECT_COLOURS.values())


def test_sealed_glassware_stands_on_a_sealed_bench_and_the_nominal_plan_succeeds():
    from sim_backends.registry import make_backend

    src = make_backend("pybullet", image_size=32, cameras=["front"], max_distractors=3)
    try:
        src.reset("pick_place_beaker_small", 5, "test_both")
        assert src.scene.appearance["texture"] in ("dots", "rings")
        assert src.execute(src.scripted_keyframes()).labels.success
    finally:
        src.close()


def test_pair_bootstrap_draws_twins_together():
    from labrobfail_vlm.bench.metrics import pair_bootstrap

    rng = np.random.default_rng(0)
    right = rng.random(200) < 0.7
    alone = pair_bootstrap(right.astype(float).tolist(), [str(i) for i in range(200)])
    twins = pair_bootstrap(np.repeat(right, 2).astype(float).tolist(), [str(i // 2) for i in range(400)])
    counted_apart = pair_bootstrap(np.repeat(right, 2).astype(float).tolist(), [str(i) for i in range(400)])
    assert alone == twins  # a pair of twins that always agree carries one sample's information, not two
    assert (counted_apart[1] - counted_apart[0]) < 0.8 * (twins[1] - twins[0])  # what counting twins apart hides
    assert twins[0] < 0.7 < twins[1]
    assert pair_bootstrap([], []) is None
    with pytest.raises(ValueError, match="3 values but 2 groups"):
        pair_bootstrap([1.0, 0.0, 1.0], ["a", "b"])


def test_every_bench_run_on_a_sealed_split_is_counted(tmp_path):
    from labrobfail_vlm.bench.evaluate import count_sealed_run, sealed_runs

    res = {"q2": 71.5, "failure_only": {"q3": 40.0, "q4": 50.0, "q5": 45.0, "q6": {"rougeL": 0.4}}}
    count_sealed_run(tmp_path, "val_both", "m", res)  # validation runs are free
    assert sealed_runs(tmp_path) == []
    for split in SEALED_SPLITS:
        count_sealed_run(tmp_path, split, "outputs/r/train/final", res)
    count_sealed_run(tmp_path, "test_both", "other", res)
    runs = sealed_runs(tmp_path)
    assert [r["split"] for r in runs] == [*SEALED_SPLITS, "test_both"]
    assert runs[-1]["source"] == "other" and runs[0]["q2"] == 71.5 and runs[0]["rougeL_failures"] == 0.4
    # benches on one dataset at once: every run counted (a read-and-rewrite ledger dropped the other's lines)
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(8) as pool:
        list(pool.map(lambda i: count_sealed_run(tmp_path, "test_scene", f"m{i}", res), range(200)))
    assert sorted(r["source"] for r in sealed_runs(tmp_path)[len(runs) :]) == sorted(f"m{i}" for i in range(200))


def test_per_type_recall_counts_q2_records_only_and_draws_pairs():
    """q2_by_type is Q2's recall per failure type over Q2 records alone: other questions of the same trajectory
    do not count, and its interval resamples pairs."""
    from labrobfail_vlm import questions as Q
    from labrobfail_vlm.bench.evaluate import score

    recs, preds, traj = [], {}, {}
    for i in range(10):  # 10 pairs: a success and a slip each; the model misses the slip in pairs 0-3
        for role, failed in (("n", False), ("i", True)):
            t = f"seen-ep{i}{role}"
            traj[t] = {"group": f"seen-pair{i}", "success": not failed, "failure_type": "object_slippage" * failed}
            q = Q.question_text("Q2", 0, "pick up the small beaker")
            recs.append({"id": f"{t}_Q2", "conversations": [{"value": q}, {"value": Q.q2_answer(0, not failed)}]})
            preds[f"{t}_Q2"] = Q.q2_answer(0, not failed or i < 4)
            recs.append({"id": f"{t}_Q1", "conversations": [{"value": "q"}, {"value": "grasp, place"}]})
            preds[f"{t}_Q1"] = "grasp, place"
    by_type = score(recs, preds, traj)["q2_by_type"]
    assert by_type["object_slippage"]["q2"] == 60.0 and by_type["object_slippage"]["n"] == 10
    assert by_type["success"] == {"q2": 100.0, "n": 10, "ci95": [100.0, 100.0]}
    lo, hi = by_type["object_slippage"]["ci95"]
    assert lo < 60.0 < hi
