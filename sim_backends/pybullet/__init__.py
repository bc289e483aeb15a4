"""PyBullet backend of LabRobFail-Sim (CPU, no display). Importing `backend` registers it."""

import os as _os


def _import_quietly() -> None:
    # pybullet's C module prints "pybullet build time: ..." on fd 2 at import; CLI errors must stay one line.
    saved = _os.dup(2)
    devnull = _os.open(_os.devnull, _os.O_WRONLY)
    try:
        _os.dup2(devnull, 2)
        import pybullet  # noqa: F401
    finally:
        _os.dup2(saved, 2)
        _os.close(saved)
        _os.close(devnull)


_import_quietly()
