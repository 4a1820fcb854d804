"""Names the recording's image codecs are configured by, in a module that imports nothing, so
that the configuration (and the docs build, which reads it from a source tree) can use them
without the generated protocol code (see :mod:`bubble_rt.io.image_codec`)."""

from __future__ import annotations

#: Colour encodings of a recording (``recording.color``): lossy first, then lossless.
COLOR_CODECS: tuple[str, ...] = ("jpeg", "png")
