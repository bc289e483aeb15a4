"""ManiSkill3 / SAPIEN backend of LabRobFail-Sim (PhysX; CPU here, GPU where ManiSkill supports it).

Importing `sim_backends.maniskill.backend` registers it as `backend=maniskill`. This package sets
ManiSkill's offline defaults before mani_skill is imported anywhere in the process: assets live in
a user cache folder (`MS_ASSET_DIR`, default `$XDG_CACHE_HOME/labrobfail/maniskill`) and ManiSkill never prompts;
a scenario whose environment would need a download is refused with a one-line error instead
(`envs.check_offline`).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

# ManiSkill keeps (and would download) assets here; a user cache, never inside the installed package
os.environ.setdefault(
    "MS_ASSET_DIR", str(Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "labrobfail" / "maniskill")
)
os.environ.setdefault("MS_SKIP_ASSET_DOWNLOAD_PROMPT", "1")

_PROBE = """
import sys
try:
    import sapien, sapien.render
except ImportError:
    sys.exit(3)
sapien.render.RenderSystem(sapien.Device("cpu"))
"""


def vulkan_problem() -> str | None:
    """Why SAPIEN finds no Vulkan device on this machine (None when it renders, or when SAPIEN is not
    installed: that is an installation error, not a missing device). Probed in a child process, as a
    machine without a Vulkan driver may crash SAPIEN rather than raise."""
    try:
        r = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        return "the SAPIEN render probe did not finish in 120 s"
    if r.returncode in (0, 3):
        return None
    lines = [ln for ln in (r.stderr or r.stdout).strip().splitlines() if ln.strip()]
    why = lines[-1] if lines else f"exit status {r.returncode}"
    return (
        f"SAPIEN found no usable Vulkan device ({why}); on Debian bookworm install mesa-vulkan-drivers "
        "and libvulkan1 from bookworm-backports (make install does)"
    )
