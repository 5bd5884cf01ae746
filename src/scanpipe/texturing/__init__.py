"""Texturing: camera frames onto the mesh (projective atlas or the paper's panorama).

- :mod:`~scanpipe.texturing.frames`: decode, place (platform angle) and choose frames.
- :mod:`~scanpipe.texturing.visibility`: occlusion tests against the mesh (Open3D ray casting).
- :mod:`~scanpipe.texturing.projective`: the best frame per face, per-point colours.
- :mod:`~scanpipe.texturing.exposure`: per-frame gains that even out seams.
- :mod:`~scanpipe.texturing.atlas`: image regions packed into PNG atlas pages, UVs.
- :mod:`~scanpipe.texturing.panorama`: the paper's eq. 17–21 and the cylindrical panorama.
"""
