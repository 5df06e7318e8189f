import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ["SDL_VIDEODRIVER"] = "offscreen"
