"""MuJoCo models without deprecated compiler attributes.

gymnasium's ``half_cheetah.xml`` sets ``<compiler settotalmass="14">``, which MuJoCo ≥ 3.3
reports on stderr (``WARNING: compiler attribute 'settotalmass' is deprecated ...``) every
time the model is compiled, i.e. once per env copy. The warning's own advice is to drop the
attribute and call ``mj_setTotalmass`` and ``mj_setConst`` on the compiled model: that gives
exactly the same model arrays and trajectories (``tests/test_families.py`` checks it), and the
stderr stays free for the warnings that matter.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import tempfile
from pathlib import Path

_TOTAL_MASS = re.compile(r'\s+settotalmass="([^"]+)"')


@functools.cache
def without_settotalmass(name: str) -> tuple[str, float]:
    """(path of a copy of gymnasium's asset ``name`` without ``settotalmass``, that total mass).

    The copy lives in the temp directory under a name derived from the stock file's content,
    so every process of a run finds the same file and an upgraded gymnasium gets a new one.
    A model that has no such attribute is returned as it is, with total mass 0 (= leave it).
    """
    # Imported here: without the MuJoCo extra the rest of the project must still import.
    import gymnasium.envs.mujoco as gym_mujoco

    stock = Path(gym_mujoco.__file__).parent / "assets" / name
    text = stock.read_text()
    found = _TOTAL_MASS.findall(text)
    if not found:
        return str(stock), 0.0
    if len(found) != 1:
        raise ValueError(f"{stock}: expected one settotalmass attribute, found {len(found)}")
    digest = hashlib.sha256(text.encode()).hexdigest()[:16]
    path = Path(tempfile.gettempdir()) / f"fedhpg-mujoco-{digest}" / name
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        # Write then rename: agents starting together never read a half-written file.
        partial = path.with_name(f".{name}.{os.getpid()}")
        partial.write_text(_TOTAL_MASS.sub("", text, count=1))
        os.replace(partial, path)
    return str(path), float(found[0])
