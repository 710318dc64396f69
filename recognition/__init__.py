"""Object recognition: VFH descriptors, camera-roll alignment and ICP (issue 5, not built yet)."""
