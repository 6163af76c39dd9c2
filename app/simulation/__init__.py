"""The simulated smart room: multi-camera recordings of people in a furnished room,
with ground truth (``smartroom simulate``, and the default source of ``smartroom run``).

Modules, each with one job:

* :mod:`~app.simulation.room` - the room, furniture, lights and calibrated cameras;
* :mod:`~app.simulation.body` - skeleton (the contract's 15 joints), joint limits,
  forward kinematics, body flesh (round cones and ellipsoids), clothes;
* :mod:`~app.simulation.paths` / :mod:`~app.simulation.motion` - walking paths and the
  choreography of everyone's activities, collision free;
* :mod:`~app.simulation.poses` - gait cycle, gestures and sitting as joint angles;
* :mod:`~app.simulation.scenes` - the scene registry (:data:`SCENES`);
* :mod:`~app.simulation.geometry` / :mod:`~app.simulation.shading` /
  :mod:`~app.simulation.render` - ray casting, textures and lighting, the renderer;
* :mod:`~app.simulation.simulator` - :class:`Simulator` and :func:`render_recording`;
* :mod:`~app.simulation.occupancy` - true body shapes and voxel occupancy;
* :mod:`~app.simulation.cache` - the rendered-once default recording;
* :mod:`~app.simulation.preview`, :mod:`~app.simulation.bench`,
  :mod:`~app.simulation.command` - preview mosaic, benchmark, CLI.

Importing this package is light; numba kernels load with the modules that use them.
"""
