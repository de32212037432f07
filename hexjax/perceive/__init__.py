"""Perception (Zhao 2018 Sect. 5): range sensors cast against each env's terrain, a 2.5D grid map fused over
time, RANSAC ground segmentation, and obstacle circles for the avoidance planner. Pure JAX below the
controllers: `sensors` (RangeSensor, presets), `raycast` (exact ray-box hits, scans), `grid` (the map),
`ransac` (the ground plane), `obstacles` (obstacle cells, components, circles)."""
