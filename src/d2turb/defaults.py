"""Defaults shared by the library and the command line's options: each CLI default is defined here once, used by
every command that has the option and shown in its ``--help`` (tests/test_cli_defaults.py). No heavy imports
here: the CLI builds its ``--help`` from these values without importing torch."""

DEFAULT_MAX_PIXELS = 178_956_970  # Pillow's own decompression-bomb error limit (2 × Image.MAX_IMAGE_PIXELS)
DEFAULT_PNG_LEVEL = 1  # of PNG outputs: ~9× faster than 6 at 256², files ~13 % larger (io.encode_png)
# `--device`: a GPU when there is one, else the CPU (the same result as `cpu` on a machine without CUDA)
DEFAULT_DEVICE = "auto"
DEVICE_HELP = "auto (a GPU when there is one), cpu, cuda or cuda:N"
# `--depth`: the weight-free prior (far = top; d2turb.depth.estimate_depth_prior), so that the simulated turbulence
# is depth-aware out of the box; `none` (uniform depth) or a map / model are asked for explicitly
DEFAULT_DEPTH = "prior"
# `simulate --batch`: images of the same size per simulator call, and at most BATCH_PIXELS pixels in all (8 images of
# 512²): bounds the blur's FFT planes
DEFAULT_BATCH = 8
BATCH_PIXELS = 1 << 21
# `--fusion` of clip restoration (d2turb.clip): before a deblur the plain mean (its blur is the mean short-exposure
# OTF that the Wiener filter models), with `--deblur none` the sharpest coefficients (+1.6 to +2.3 dB over the mean on
# the validation and test clips; docs/clips.md, "Sharpest-coefficient fusion")
CLIP_FUSIONS = ("mean", "robust", "fba", "sharpest")
DEFAULT_FUSION = "mean"
FUSION_WITHOUT_DEBLUR = "sharpest"
# the clip pipeline's window (d2turb.clip.DEFAULT_TEMPORAL, ClipRestorer's), the default of `evaluate --real-clips
# --temporal`: 24 since the clip core (1c2dcab); not re-measured against 32
DEFAULT_TEMPORAL = 24
# the window of docs/clips.md's validation and test figures, hence `evaluate --clips`' default and the page's Clip tab
MEASURED_TEMPORAL = 32
# `restore --tile`, Restorer's, the page's: 512² tiles restore a 1080p frame as fast as untiled, in 0.6 GiB instead
# of 1.5 (benchmarks/RESULTS.md, "One 1920×1080 frame with the shipped model")
DEFAULT_TILE_PX = 512
# `restore --overlap`: pixels neighbouring tiles share; a jump Δ between them leaves a step ≤ Δ·π/overlap
# (docs/restore.md, "Any size: tiling without seams")
DEFAULT_OVERLAP_PX = 64
# D/r0 of TurbulenceParams, the page's slider and its clip simulated from an image: the middle of the medium bin
# (2.25–3.75, d2turb.sim.params.BINS)
DEFAULT_DR0 = 3.0
# `evaluate --real-clips --max-frames`: frames read per clip (the 1080p clip costs about 1 s of CPU per frame)
DEFAULT_REAL_CLIP_FRAMES = 48
# the default optics (d2turb.sim.Optics, TurbulenceParams, `--aperture`, `--wavelength`, `--path-length`, the page):
# aperture D, wavelength λ, and the simulator's path length L; the pixel angle ifov defaults to Nyquist λ/(2D)
DEFAULT_APERTURE_M = 0.1
DEFAULT_WAVELENGTH_M = 525e-9
DEFAULT_PATH_LENGTH_M = 1000.0
# pixels per λ/D at Nyquist sampling (ifov = λ/(2D)): what the clip deblur and registration_dr0 take when the pixel
# angle is not known
NYQUIST_LAMBDA_OVER_D_PX = 2.0
