"""What ``update_path="auto"`` and ``storage="auto"`` pick on a CUDA device.

The fast path (the update replayed as a CUDA graph, the replay buffer's transitions on the GPU) is the default on CUDA
since the device check (``benchmarks/gpu_check.sh``) passed on a GPU (``docs/results/gpu_check.json``). Set
:data:`FAST_PATH_BY_DEFAULT` to False, or pass ``update_path="eager"`` and
``replay_buffer_kwargs=dict(storage="host")``, for the eager update and the host's replay buffer on CUDA as on the
CPU. It changes nothing on the CPU.
"""

FAST_PATH_BY_DEFAULT = True
"""True: ``"auto"`` takes the CUDA graph (where the update's hooks allow it) and the GPU's replay storage on CUDA."""
