"""Diagnose one trajectory: keyframe grid in, one JSON diagnosis out (labrobfail_vlm/infer.py; `--help` lists
every setting).

Run as:
    python infer.py --grid frames.png --task "pick up the beaker" [--model DIR] [--json OUT]
    python infer.py --frames DIR --task "press the red button" --q6-mode template --objects "red button"
"""

from labrobfail_vlm.infer import cli

if __name__ == "__main__":
    cli()
