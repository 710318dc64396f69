"""The offline solve: a recorded log in, one batch solution and the files people and tools read out.

- ``solve``: the pure core (frame blocks in, ``ResolveResult`` out).
- ``logs``: MCAP -> validated frame blocks, in one pass.
- ``outputs``: object markers placed through the solved cameras, ``resolved.mcap`` and TUM files.
- ``pipeline``: ``resolve_log`` ties them together (what ``cellsight resolve`` calls).

The solve reads marker observations only; a caller that evaluates gets every other message
through ``on_message`` during the same pass.
"""
