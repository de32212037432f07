"""The world a hexapod walks in: robot specs and kinematics, terrain families and their batched sampling,
elevation maps, and the presets of both as YAML files under configs/.

robot    RobotSpec, leg frames, forward and inverse kinematics (JAX)
terrain  TerrainSpec, batched generators, padding, obstacle circles, height maps
dem      2.5D elevation grids rasterised from terrains (Chen 2019's map)
presets  YAML presets: configs/robots, configs/terrains, checked on load
"""
