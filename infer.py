"""Diagnose one trajectory: keyframe grid in, one JSON diagnosis out (stdout).

Run as:
    python infer.py --grid frames.png [--task "pick up the beaker ..."] [--model DIR] [--json OUT]
    python infer.py --frames DIR --task "press the red button"      # DIR/<view>/<frame>.png -> grid
    python infer.py --grid frames.png --six-prompts                  # no shared-prefix KV cache
    python infer.py --grid frames.png --task "..." --q6-mode template --objects "small beaker,target area"
    python infer.py --grid frames.png --task "..." --endpoint http://127.0.0.1:8000/v1   # a vLLM server (README)

Without --model it uses the checkpoint `make demo` trains (outputs/demo_train/final). With --endpoint the
questions go to an OpenAI-compatible server instead (its key, if any, from $OPENAI_API_KEY or --endpoint-key-env).
Any bad input (file, folder, model directory, unreachable endpoint) gives one line on stderr and exit code 2, and
every argument is checked before inference starts: the model directory is validated without building a tensor
(config, size against --max-model-gb / $LABROBFAIL_MAX_MODEL_GB, default half the machine's memory, and weights),
and --json must name a file in a folder this process can write.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from labrobfail_vlm.config import ConfigError, cli_main  # noqa: E402

DEFAULT_MODEL = "outputs/demo_train/final"


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2, like every other bad input
        raise ConfigError(f"usage: {message}")


def output_file(path: str) -> Path:
    """--json, checked before inference: a file name (not a folder) in an existing folder this process can write.
    Writability is probed by creating and removing a uniquely named file there: permission bits say nothing for
    root, read-only mounts or /proc, and the probe leaves nothing behind."""
    out = Path(path)
    if out.is_dir():
        raise ConfigError(f"--json: {path} is a directory; give a file name for the diagnosis")
    if not out.parent.is_dir():
        raise ConfigError(f"--json: folder {out.parent} does not exist")
    try:
        fd, probe = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name[:64]}.", suffix=".probe")
    except OSError as e:
        raise ConfigError(f"--json: cannot write {path} ({e.strerror or type(e).__name__})") from None
    os.close(fd)
    os.unlink(probe)
    return out


def write_output(out: Path, text: str) -> None:
    """Atomic write; if it fails after all (disk full), the temp file goes too and the error names the file."""
    from labrobfail_vlm.io import atomic_write_bytes

    try:
        atomic_write_bytes(out, (text + "\n").encode())
    except OSError as e:
        out.with_name(out.name + ".tmp").unlink(missing_ok=True)
        raise ConfigError(f"--json: cannot write {out} ({e.strerror or type(e).__name__})") from None


def main(argv: list[str]) -> int:
    ap = _Parser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--grid", help="a keyframe grid image (as built by labrobfail_vlm.grid)")
    src.add_argument("--frames", help="folder with one sub-folder of keyframe images per camera view")
    ap.add_argument("--task", default="", help="the task in words (the {task_name} of the prompt)")
    ap.add_argument("--model", default=None, help="fine-tuned checkpoint, merged model or Qwen3-VL dir")
    ap.add_argument("--endpoint", help="an OpenAI-compatible server's base URL (e.g. vLLM: http://HOST:8000/v1)")
    ap.add_argument("--endpoint-model", help="the served model's name (default: the one the server lists)")
    ap.add_argument("--endpoint-key-env", default="OPENAI_API_KEY", help="environment variable with its API key")
    ap.add_argument("--json", help="also write the diagnosis to this file (atomically)")
    ap.add_argument("--num-frames", type=int, default=None,
                    help="keyframes in the grid (default: the grid the model was trained on, else 16)")
    ap.add_argument("--six-prompts", action="store_true", help="encode the image once per question")
    ap.add_argument("--q6-mode", choices=("free", "template"), default="free",
                    help="Q6 as free text, or the most likely correction strategy of the paper's table")
    ap.add_argument("--objects", default="", help="comma-separated object/place names of the scene (template mode)")
    ap.add_argument("--max-model-gb", type=float, default=None,
                    help="refuse models whose weights would take more (default: $LABROBFAIL_MAX_MODEL_GB, else half "
                         "the machine's memory)")
    a = ap.parse_args(argv)

    from labrobfail_vlm.images import load_frames, load_image

    if a.endpoint and a.model:
        raise ConfigError("--model/--endpoint: give one of them, not both")
    if a.num_frames is not None and a.num_frames < 1:
        raise ConfigError(f"--num-frames: expected a positive integer, got {a.num_frames}")
    out = output_file(a.json) if a.json else None
    model = a.model or DEFAULT_MODEL
    if not a.endpoint:
        from labrobfail_vlm.train.checkpoint import validate_checkpoint

        if not Path(model).is_dir():
            raise ConfigError(f"--model: no such model directory {model!r}"
                              + (" (run `make demo` to train the default one)" if model == DEFAULT_MODEL else ""))
        validate_checkpoint(model, "--model", a.max_model_gb)  # before any tensor is built
    image = load_image(a.grid) if a.grid else None
    frames = load_frames(a.frames)[1] if a.frames else None

    if a.endpoint:
        from labrobfail_vlm.endpoint import EndpointAnalyzer

        fa = EndpointAnalyzer(a.endpoint, a.endpoint_model, a.endpoint_key_env, q6_mode=a.q6_mode)
    else:
        from labrobfail_vlm.analyzer import FailureAnalyzer

        fa = FailureAnalyzer.from_pretrained(model, q6_mode=a.q6_mode, max_model_gb=a.max_model_gb)
    diag = fa.analyze(image if image is not None else frames, task=a.task, one_pass=not a.six_prompts,
                      frames=a.num_frames, objects=[o.strip() for o in a.objects.split(",") if o.strip()])
    text = diag.to_json()
    if out is not None:
        write_output(out, text)
    print(text)
    return 0


if __name__ == "__main__":
    cli_main(main)
