"""What ``update_path="auto"`` and ``storage="auto"`` pick on a CUDA device.

The fast path (the update replayed as a CUDA graph, the replay buffer's transitions on the GPU) is built and tested on
the CPU, but has not run on a GPU yet. Until the device check (``benchmarks/gpu_check.sh``) has passed on one,
:data:`FAST_PATH_BY_DEFAULT` is False: ``"auto"`` takes the eager update and the host's replay buffer on CUDA as on
the CPU, and the fast path is opt-in (``update_path="cuda_graph"``, ``replay_buffer_kwargs=dict(storage="device")``).
The check's benchmark sets it to measure what ``"auto"`` would then pick; it changes nothing on the CPU.
"""

FAST_PATH_BY_DEFAULT = False
"""True: ``"auto"`` takes the CUDA graph (where the update's hooks allow it) and the GPU's replay storage on CUDA."""
