"""Register the dsm plugins even where their entry points are not declared yet."""
import sys
from pathlib import Path

import fwk.plugins as _plugins

try:
    import fwk_dsm  # noqa: F401
except ImportError:  # an editable install made before the package existed
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "plugins"))


def _ensure():
    reg = _plugins.get_registry()
    try:
        reg.get("model", "dsm")
        reg.get("task", "interpolate")
    except Exception:
        import fwk_dsm
        import fwk_dsm_tasks

        _plugins._REGISTRY = _plugins.registry_from(fwk_dsm, fwk_dsm_tasks, load_entrypoints=True)


_ensure()
