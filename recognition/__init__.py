"""Object recognition: VFH descriptors, camera-roll alignment and ICP (docs/design/recognition.md).

Pure cores: ``cloud`` (depth -> cloud, normals), ``vfh``, ``align`` (roll histogram, ICP),
``segment``, ``models`` (the database), ``pipeline`` (one frame -> detections).
``worker`` wraps them in a zenoh service.
"""
