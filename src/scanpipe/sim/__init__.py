"""The virtual rig: a ground-truth scene, ray-cast sensor models and device emulators.

- :mod:`scanpipe.sim.scene`: :class:`~scanpipe.sim.scene.Scene` and ``load_scene()`` (OBJ,
  GLB, glTF); :mod:`scanpipe.sim.room`: the built-in scenes (``builtin_room()``,
  ``box_room()``) and ``resolve_scene()`` (a built-in name or a file).
- :mod:`scanpipe.sim.scanner`, :mod:`scanpipe.sim.motion`, :mod:`scanpipe.sim.camera`: the
  scanner's ranges and measurement model, the motor's motion, the camera renderer.
- :mod:`scanpipe.sim.controller` (the motor controller firmware, docs/motor-link.md) and
  :mod:`scanpipe.sim.ldoem_device` (the LD-OEM's request handling): pure state machines.
- :mod:`scanpipe.sim.emulators`: the same on real endpoints (TCP, pty, a capture interface),
  sharing :class:`~scanpipe.sim.clock.SimClock` and one platform.
- :mod:`scanpipe.sim.direct`: ``simulate_direct`` (a recording without sockets);
  :mod:`scanpipe.sim.session` plans its timeline; :mod:`scanpipe.sim.truth` the truth folder;
  :mod:`scanpipe.sim.options`: :class:`~scanpipe.sim.options.SimOptions`.

See docs/simulation.md.
"""
