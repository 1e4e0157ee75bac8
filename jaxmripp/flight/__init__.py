"""Physics in the loop: the onboard runtime flies simulated quadrotors in a 3D city.

    python -m jaxmripp.flight --export pretrained/default --out runs/flight

The physics is pybullet's (the engine of gym-pybullet-drones, on which the paper flew its
planner), installed with the `flight` extra. Modules: `city` (the voxel world in metres,
same seed, same city), `quadrotor` (a rigid-body drone and its position controller),
`scene` (the pybullet world: depth camera by ray casting, window sightings, contacts),
`mission` (one mission: planners, radio, flights), `pictures` (3D plot and GIF) and
`team` (an export with its world, take-off pads, radio delivery). Only `scene`, `quadrotor` and the
missions need pybullet; it is imported when a scene is built.
"""
