"""File formats for results: one module per format, each a pure function returning bytes.

:mod:`scanpipe.exporters.model` turns artifact tables into :class:`MeshModel` /
:class:`CloudModel`; the format modules turn those into ``{file name: bytes}``;
:mod:`scanpipe.stages.export` chooses, checks and writes atomically.
"""
