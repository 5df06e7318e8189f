"""hydrabench.sim: traffic and world model (highway-env traffic, contexts, one physical weather state).

Bottom layer of `sim <- sensors <- fusion <- study`: imports nothing from the other packages.
"""

import os

# highway-env renders black frames with SDL's "dummy" driver; "offscreen" works headless.
if os.environ.get("SDL_VIDEODRIVER", "dummy") == "dummy":
    os.environ["SDL_VIDEODRIVER"] = "offscreen"
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
