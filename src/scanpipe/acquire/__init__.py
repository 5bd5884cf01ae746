"""Acquisition on the robot: device drivers and the recorder behind ``scanpipe record``.

- :mod:`scanpipe.acquire.scanner_client`: the scanner's TCP link (``ldoem`` and ``paper``).
- :mod:`scanpipe.acquire.motor_client`: the motor controller's serial link (docs/motor-link.md).
- :mod:`scanpipe.acquire.cameras`: frame capture (OpenCV or the virtual camera), JPEG, timestamps.
- :mod:`scanpipe.acquire.recorder`: the scan procedures (step-and-scan, continuous), events,
  file splitting, stopping on signals, the summary.
- :mod:`scanpipe.acquire.display`: the live progress display (rich).
"""
