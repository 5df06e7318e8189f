"""hydrabench.sim: traffic and world model (highway-env traffic, contexts, one physical weather state).

Bottom layer of `sim <- sensors <- fusion <- study`: imports nothing from the other packages.
"""

import importlib
import importlib.util
import os
import sys
import types

# highway-env renders black frames with SDL's "dummy" driver; "offscreen" works headless.
if os.environ.get("SDL_VIDEODRIVER", "dummy") == "dummy":
    os.environ["SDL_VIDEODRIVER"] = "offscreen"
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")


class _DeferredPyplot(types.ModuleType):
    """Stands in for matplotlib.pyplot until an attribute is used, then imports the real module."""

    def __getattr__(self, attr):
        if sys.modules.get("matplotlib.pyplot") is self:
            del sys.modules["matplotlib.pyplot"]
        real = importlib.import_module("matplotlib.pyplot")
        return getattr(real, attr)


def _defer_pyplot() -> None:
    """Import matplotlib.pyplot on first use instead of at import.

    highway-env imports pyplot at the top of `highway_env.vehicle.dynamics` for a plotting helper
    we never call; pyplot's own imports (figure, font manager, fontTools, mplot3d) were ~40 % of
    matplotlib's share of every generation worker's start-up. Code that plots gets the real module
    on first access (`importlib.util.LazyLoader` cannot do this on Python 3.11: the import
    statement itself reads `__spec__` and so triggers the load).
    """
    if "matplotlib.pyplot" not in sys.modules and importlib.util.find_spec("matplotlib") is not None:
        sys.modules["matplotlib.pyplot"] = _DeferredPyplot("matplotlib.pyplot")


_defer_pyplot()
