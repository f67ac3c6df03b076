"""nerfstudio integration of S2CamP: camera optimizer, data manager, model and pipeline."""

from s2camp_ns.bundled_ffmpeg import make_bundled_ffmpeg_findable

# nerfstudio's render commands need an `ffmpeg` on PATH; loading an s2camp run imports this package first, so the
# environment's own `ffmpeg` script is found even when the environment is not activated (s2camp_ns/bundled_ffmpeg.py).
make_bundled_ffmpeg_findable()
