"""Scanner wire formats: stream framing with resync, one module per dialect, the dialect registry.

- :mod:`scanpipe.protocol.profile`: :class:`Profile`, one decoded scanner sector.
- :mod:`scanpipe.protocol.framing`: ``marker, u32 length, payload, XOR`` framing with resync.
- :mod:`scanpipe.protocol.paper`: the frame printed in the paper (SICK CoLa-B framing).
- :mod:`scanpipe.protocol.ldoem`: the SICK LD-OEM 1000's own TCP protocol.
- :mod:`scanpipe.protocol.registry`: ``DIALECTS``, :class:`StreamDecoder`, auto-detection.
"""
