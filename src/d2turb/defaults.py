"""Defaults shared by the library and the command line's options. No heavy imports here: the CLI builds its
``--help`` from these values without importing torch."""

DEFAULT_MAX_PIXELS = 178_956_970  # Pillow's own decompression-bomb error limit (2 × Image.MAX_IMAGE_PIXELS)
DEFAULT_PNG_LEVEL = 1  # of PNG outputs: ~9× faster than 6 at 256², files ~13 % larger (io.encode_png)
DEVICE_HELP = "auto (a GPU when there is one), cpu, cuda or cuda:N"
