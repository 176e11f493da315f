"""Make sure the blendshape plugins are registered even where their entry points are not
declared yet (an editable install made before they were added)."""
import sys
from pathlib import Path

import fwk.plugins as _plugins

try:
    import fwk_pb  # noqa: F401
except ImportError:  # an editable install made before the package existed
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "plugins"))


def _ensure():
    reg = _plugins.get_registry()
    try:
        reg.get("model", "pb")
        reg.get("task", "blendshapes")
    except Exception:
        import fwk_blendshapes
        import fwk_dt
        import fwk_pb

        mods = [fwk_pb, fwk_blendshapes]
        _plugins._REGISTRY = _plugins.registry_from(*mods, load_entrypoints=True)


_ensure()
