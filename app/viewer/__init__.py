"""The meshcat viewer's scene, as plain code: geometry of what is drawn
(:mod:`app.viewer.geometry`), meshcat commands and three.js objects
(:mod:`app.viewer.three`), the scene that turns results into commands
(:mod:`app.viewer.scene`), and meshcat's server run inside the viewer process
(:mod:`app.viewer.server`). The worker shell is :mod:`workers.viewer`."""
