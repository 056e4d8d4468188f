import os

# pygame: no audio device on CI machines. (Not SDL_VIDEODRIVER=dummy: highway-env then draws nothing.)
os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
os.environ.setdefault("XDG_RUNTIME_DIR", "/tmp")
