"""``make gpu-check``: one command that proves the CUDA path on a machine with a GPU (docs/GPU-CHECK.md).

- ``config``: the command's options and the scene (mip-NeRF 360 room at images_4 size);
- ``environment``: what the machine has (CUDA devices, tiny-cuda-nn, nvcc, gsplat) and the refusal without CUDA;
- ``measured_train``: ``ns-train`` in-process with per-step CUDA timing and the peak CUDA memory of the run;
- ``runs``: the training runs, their evaluation and the 2-process NCCL run;
- ``stock_nerfacto``: the camera interface S2CamP's evaluation needs, for a stock ``nerfacto`` run;
- ``report``: the markdown tables;
- ``cli``: the stages in order and the exit status (``python -m s2camp_ns.benchmarks.gpu_check``).
"""
