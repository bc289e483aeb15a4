"""Diagnose one trajectory: keyframe grid in, one JSON diagnosis out (stdout). The code behind infer.py and the
`labrobfail-infer` console script.

Run as:
    python infer.py --grid frames.png [--task "pick up the beaker ..."] [--model DIR] [--json OUT]
    python infer.py --frames DIR --task "press the red button"      # DIR/<view>/<frame>.png -> grid
    labrobfail-infer --video front.mp4 --video side.mp4 --task "pick up the small beaker"   # one video per view
    labrobfail-infer --video front.mp4 --video side.mp4 --keyframes motion
    python infer.py --grid frames.png --six-prompts                  # no shared-prefix KV cache
    python infer.py --grid frames.png --task "..." --q6-mode template --objects "small beaker,target area"
    python infer.py --grid frames.png --task "..." --endpoint http://127.0.0.1:8000/v1   # a vLLM server (docs/GUIDE.md)
    labrobfail-infer grid=frames.png task="press the red button"

Without a model it uses the checkpoint `make demo` trains (outputs/demo_train/final). With an endpoint the
questions go to an OpenAI-compatible server instead (its key, if any, from $OPENAI_API_KEY or endpoint_key_env).
Any bad input (file, folder, model directory, unreachable endpoint) gives one line on stderr and exit code 2, and
every setting is checked before inference starts: the model directory is validated without building a tensor
(config, size against max_model_gb / $LABROBFAIL_MAX_MODEL_GB, default half the machine's memory, and weights),
and json must name a file in a folder this process can write. Defaults: configs/infer.yaml.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from labrobfail_vlm.config import ConfigError, cli_main, is_int, load_config

DEFAULT_MODEL = "outputs/demo_train/final"


def output_file(path: str) -> Path:
    """json, checked before inference: a file name (not a folder) in an existing folder this process can write.
    Writability is probed by creating and removing a uniquely named file there: permission bits say nothing for
    root, read-only mounts or /proc, and the probe leaves nothing behind."""
    out = Path(path)
    if out.is_dir():
        raise ConfigError(f"json: {path} is a directory; give a file name for the diagnosis")
    if not out.parent.is_dir():
        raise ConfigError(f"json: folder {out.parent} does not exist")
    try:
        fd, probe = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name[:64]}.", suffix=".probe")
    except OSError as e:
        raise ConfigError(f"json: cannot write {path} ({e.strerror or type(e).__name__})") from None
    os.close(fd)
    os.unlink(probe)
    return out


def write_output(out: Path, text: str) -> None:
    """Atomic write; if it fails after all (disk full), the error names the file (the temp file is already gone)."""
    from labrobfail_vlm.io import atomic_write_bytes

    try:
        atomic_write_bytes(out, (text + "\n").encode())
    except OSError as e:
        raise ConfigError(f"json: cannot write {out} ({e.strerror or type(e).__name__})") from None


def split_videos(argv: list[str]) -> tuple[list[str], list[str]]:
    """`--video a.mp4 --video b.mp4` (or video=a.mp4 ...; one per camera view, in the grid's view order): the other
    arguments and the videos, which a key=value setting could hold only once."""
    rest, videos, i = [], [], 0
    while i < len(argv):
        arg = argv[i]
        if arg == "--video" and i + 1 < len(argv):
            videos.append(argv[i + 1])
            i += 2
            continue
        for flag in ("--video=", "video="):
            if arg.startswith(flag):
                videos.append(arg[len(flag) :])
                break
        else:
            rest.append(arg)
        i += 1
    return rest, videos


def _check(a) -> None:
    """Every setting's type and the grid/frames/video choice, before anything is read or loaded."""
    for key in ("grid", "frames", "model", "endpoint", "endpoint_model", "json"):
        if a[key] is not None and not isinstance(a[key], str):
            raise ConfigError(f"{key}: expected a path or text, got {a[key]!r}")
    if sum(x is not None for x in (a.grid, a.frames, a.video)) != 1:
        raise ConfigError("grid/frames/video: give one of them (grid=IMAGE, frames=FOLDER or --video FILE per view)")
    if a.keyframes not in ("uniform", "motion"):
        raise ConfigError(f"keyframes: expected uniform or motion, got {a.keyframes!r}")
    if a.num_frames is not None and not is_int(a.num_frames, 1):
        raise ConfigError(f"num_frames: expected a positive integer, got {a.num_frames!r}")
    if a.q6_mode not in ("free", "template"):
        raise ConfigError(f"q6_mode: expected free or template, got {a.q6_mode!r}")
    if a.max_model_gb is not None and (
        isinstance(a.max_model_gb, bool) or not isinstance(a.max_model_gb, (int, float))
    ):
        raise ConfigError(f"max_model_gb: expected a number of GB, got {a.max_model_gb!r}")


def main(argv: list[str]) -> int:
    argv, videos = split_videos(argv)
    a = load_config("infer.yaml", argv)
    a.video = videos or None
    _check(a)

    from labrobfail_vlm.images import load_frames, load_image
    from labrobfail_vlm.video import keyframes, scan

    if a.endpoint and a.model:
        raise ConfigError("model/endpoint: give one of them, not both")
    out = output_file(a.json) if a.json else None
    model = a.model or DEFAULT_MODEL
    if not a.endpoint:
        from labrobfail_vlm.train.checkpoint import validate_checkpoint

        if not Path(model).is_dir():
            raise ConfigError(
                f"model: no such model directory {model!r}"
                + (" (run `make demo` to train the default one)" if model == DEFAULT_MODEL else "")
            )
        validate_checkpoint(model, "model", a.max_model_gb)  # before any tensor is built
    image = load_image(a.grid) if a.grid else None
    frames = load_frames(a.frames)[1] if a.frames else None
    clips = [scan(v, "video") for v in videos]  # every frame checked before the model loads

    if a.endpoint:
        from labrobfail_vlm.endpoint import EndpointAnalyzer

        fa = EndpointAnalyzer(a.endpoint, a.endpoint_model, a.endpoint_key_env, q6_mode=a.q6_mode)
    else:
        from labrobfail_vlm.analyzer import FailureAnalyzer

        fa = FailureAnalyzer.from_pretrained(model, q6_mode=a.q6_mode, max_model_gb=a.max_model_gb)
    if clips:  # the grid the model was trained on: its number of keyframes (or num_frames)
        frames = keyframes(clips, a.num_frames or getattr(fa, "num_frames", 8), a.keyframes)
    diag = fa.analyze(
        image if image is not None else frames,
        task=a.task,
        one_pass=not a.six_prompts,
        frames=a.num_frames,
        objects=[o.strip() for o in str(a.objects).split(",") if o.strip()],
    )
    text = diag.to_json()
    if out is not None:
        write_output(out, text)
    print(text)
    return 0


def cli() -> None:
    """The `labrobfail-infer` console script."""
    cli_main(main, __doc__)
