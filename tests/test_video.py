"""Video in: a real PyBullet episode written as MP4 (one file per view), keyframes picked uniformly in time and by
motion, the diagnosis from video equal to the one from the same keyframes, and bad or truncated video refused in
one line by labrobfail-infer."""

import io
import json

import numpy as np
import pytest
from conftest import cli, run, run_here
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image
from serve_fixtures import mixed_model  # noqa: F401  (fixture)

from labrobfail_vlm.config import ConfigError
from labrobfail_vlm.video import pick, read_keyframes, scan

STILL = 24  # frames the first keyframe is held for: a robot that waits before it moves
HOLD = 3  # frames every later keyframe is held for


@pytest.fixture(scope="module")
def episode_videos(tmp_path_factory):
    """A scripted PyBullet episode's keyframes (front and side, 96 px) and each view as an MP4: the first keyframe
    held STILL frames, every other HOLD frames, so a video frame index maps back to its keyframe. Returns the MP4s
    and the keyframes per view."""
    import cv2

    from sim_backends import make_backend

    src = make_backend("pybullet", image_size=96)
    src.reset("pick_place_beaker_small", 3, "seen")  # 8 keyframes: more than a 4-keyframe pick
    ep = src.execute(src.scripted_keyframes())
    src.close()
    views = [[np.asarray(Image.open(io.BytesIO(b)).convert("RGB")) for b in view if b] for view in ep.images[:2]]
    out = tmp_path_factory.mktemp("video")
    paths = []
    for name, frames in zip(("front", "side"), views):
        path = out / f"{name}.mp4"
        w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (96, 96))
        assert w.isOpened()
        for k, f in enumerate(frames):
            for _ in range(STILL if k == 0 else HOLD):
                w.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
        w.release()
        paths.append(path)
    return paths, views


def test_uniform_and_motion_keyframes_of_a_rendered_episode(episode_videos):
    import cv2

    paths, keyframes = episode_videos
    info = scan(paths[0])
    n = STILL + HOLD * (len(keyframes[0]) - 1)
    assert info.frames == n and (info.width, info.height) == (96, 96)
    uniform, motion = pick(info.motion, 8, "uniform"), pick(info.motion, 8, "motion")
    for picks in (uniform, motion):
        assert picks[0] == 0 and picks[-1] == n - 1 and picks == sorted(set(picks)) and len(picks) == 8
    assert uniform == np.linspace(0, n - 1, 8).round().astype(int).tolist()
    # the lead-in is still: uniform spends keyframes on it, motion only its first frame
    assert sum(i < STILL for i in uniform) >= 3 and sum(i < STILL for i in motion) <= 2, (uniform, motion)
    assert [len(v) for v in read_keyframes(paths, 8, "motion")] == [8, 8]  # both views (picked on summed motion)
    # one view's keyframes are exactly its video frames at the picked indices, and those show the rendered keyframes
    for path, keys in zip(paths, keyframes):
        view = read_keyframes([path], 8, "motion")[0]
        motion = pick(scan(path).motion, 8, "motion")
        cap, decoded = cv2.VideoCapture(str(path)), []
        while (got := cap.read())[0]:
            decoded.append(cv2.cvtColor(got[1], cv2.COLOR_BGR2RGB))
        cap.release()
        for img, i in zip(view, motion):
            assert np.array_equal(np.asarray(img), decoded[i]), i  # exactly video frame i
            if i >= STILL and (i - STILL) % HOLD == 0:
                continue  # mp4v is lossy, most of all on the first frame after a change: checked on held frames
            errs = [np.abs(np.asarray(img, np.float32) - k.astype(np.float32)).mean() for k in keys]
            assert int(np.argmin(errs)) == (0 if i < STILL else 1 + (i - STILL) // HOLD), (i, errs)


def test_analyze_video_equals_the_diagnosis_of_its_keyframes(episode_videos, mixed_model):  # noqa: F811
    from labrobfail_vlm.analyzer import FailureAnalyzer

    paths, _ = episode_videos
    fa = FailureAnalyzer.from_pretrained(mixed_model)
    for mode in ("uniform", "motion"):
        got = fa.analyze_video(paths, task="pick up the small beaker", keyframes=mode)
        want = fa.analyze(read_keyframes(paths, fa.num_frames, mode), task="pick up the small beaker")
        assert got == want
    r = run_here(  # in this process: the bad-video cases below run labrobfail-infer --video as a process
        [cli("infer"), "--video", str(paths[0]), "--video", str(paths[1]), "--keyframes", "motion"]
        + ["--task", "pick up the small beaker", "--model", str(mixed_model)]
    )
    assert r.returncode == 0, r.stderr[-1000:]
    assert json.loads(r.stdout) == json.loads(got.to_json())


@given(st.lists(st.floats(0, 50, allow_nan=False), min_size=1, max_size=80), st.integers(1, 16))
def test_picks_are_distinct_ordered_and_span_the_video(motion, m):
    for mode in ("uniform", "motion"):
        p = pick(np.asarray(motion), m, mode)
        assert p == sorted(set(p)) and len(p) == min(m, len(motion)) and p[-1] == len(motion) - 1
        assert p[0] == 0 or m == 1


def test_bad_and_truncated_videos_are_one_line_errors(episode_videos, mixed_model, tmp_path):  # noqa: F811
    import cv2

    paths, _ = episode_videos
    data = paths[0].read_bytes()
    (tmp_path / "cut.mp4").write_bytes(data[: len(data) // 2])  # the MP4 index (moov) is at the end: gone
    (tmp_path / "text.mp4").write_bytes(b"hello, I am not a video")
    avi = tmp_path / "whole.avi"  # an AVI states its frame count up front: a cut one decodes fewer
    w = cv2.VideoWriter(str(avi), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 64))
    for i in range(20):
        w.write(np.random.default_rng(i).integers(0, 255, (64, 64, 3), dtype=np.uint8))
    w.release()
    (tmp_path / "cut.avi").write_bytes(avi.read_bytes()[: int(avi.stat().st_size * 0.6)])
    Image.new("RGB", (64, 64)).save(tmp_path / "still.png")  # FFmpeg opens a still as a one-frame video
    cases = [
        (["--video", str(tmp_path / "cut.mp4")], "header is truncated"),
        (["--video", str(tmp_path / "text.mp4")], "not a video"),
        (["--video", str(tmp_path / "cut.avi")], "truncated or corrupt"),
        (["--video", str(tmp_path / "gone.mp4")], "does not exist"),
        (["--video", str(tmp_path / "still.png")], "is a PNG image, not a video"),
        (["--video", str(paths[0]), "--grid", str(paths[0])], "give one of them"),
        (["--video", str(paths[0]), "--keyframes", "random"], "keyframes: expected uniform or motion"),
    ]
    for i, (args, needle) in enumerate(cases):
        call = run_here if i else run  # the first case as a real process, the rest in this one
        r = call([cli("infer"), *args, "--model", str(mixed_model)])
        assert r.returncode == 2 and needle in r.stderr, (args, r.returncode, r.stderr[-500:])
        assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr
    # an animated GIF is a video to FFmpeg (Pillow reads it too): only a one-frame still is refused as an image
    frames = [Image.new("RGB", (64, 64), (i * 12, 0, 0)) for i in range(20)]
    frames[0].save(tmp_path / "moving.gif", save_all=True, append_images=frames[1:], duration=100)
    assert scan(tmp_path / "moving.gif").frames == 20
    with pytest.raises(ConfigError, match="truncated or corrupt"):
        scan(tmp_path / "cut.avi")
    with pytest.raises(ConfigError, match="has more than 10 frames"):  # the server's bound on decoding
        scan(avi, max_frames=10)
    assert scan(avi, max_frames=20).frames == 20


def test_a_grid_of_another_size_is_fitted_to_the_models_or_refused(mixed_model):  # noqa: F811
    """A checkpoint that names its grid: a larger grid of the same layout is read at the trained size (the same
    diagnosis as the grid resized by hand), another layout is a one-line ConfigError."""
    from serve_fixtures import frame_lists

    from labrobfail_vlm.analyzer import FailureAnalyzer, frames_to_grid
    from labrobfail_vlm.grid import GridConfig, fit_grid

    trained = GridConfig(width=256, height=128, max_frames=8, columns=4)
    fa = FailureAnalyzer.from_pretrained(mixed_model, grid=trained, fit=True)
    big = frames_to_grid(frame_lists(4), GridConfig(width=768, height=384, max_frames=8, columns=4))
    assert fa.analyze(big, "stir the solution") == fa.analyze(fit_grid(big, trained), "stir the solution")
    assert fit_grid(big, trained).size == (256, 128)
    with pytest.raises(ConfigError, match=r"a 512x512 image is not the 256x128 layout") as e:
        fa.analyze(Image.new("RGB", (512, 512)), "stir the solution")
    assert "\n" not in str(e.value)


def test_the_server_form_fits_or_refuses_a_grid_before_it_is_queued():
    """The diagnosis server checks the layout from the image header (a 400 before decoding, never a 500 from the
    model thread) and resizes a grid of the right shape in its decode step."""
    from labrobfail_vlm.grid import GridConfig
    from labrobfail_vlm.serve.form import Upload, build, plan

    def upload(w, h):
        buf = io.BytesIO()
        Image.new("RGB", (w, h), (90, 120, 150)).save(buf, format="PNG")
        return [("grid", Upload("g.png", buf.getvalue()))]

    trained = GridConfig(width=256, height=128, max_frames=8, columns=4)
    with pytest.raises(ConfigError, match="a 300x300 image is not the 256x128 layout"):
        plan(upload(300, 300), trained, fit=True)
    assert build(plan(upload(512, 256), trained, fit=True), trained).grid.size == (256, 128)
    assert build(plan(upload(300, 300), trained), trained).grid.size == (300, 300)  # a model that names no grid
