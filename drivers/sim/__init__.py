"""The simulated work cell: scenario files, ray-cast RGB-D rendering, Kinect v1 noise, motion."""
