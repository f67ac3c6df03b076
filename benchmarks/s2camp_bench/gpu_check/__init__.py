"""The GPU check and the regime command: what one lent GPU answers, within one lease (docs/GPU-CHECK.md).

- ``config``: the check's options, its scene and the layout of its folder;
- ``environment``: what the machine has (CUDA devices, tiny-cuda-nn, nvcc, gsplat) and the refusal without CUDA;
- ``processes``: the deadline, and commands as subprocesses with a log and a time limit;
- ``records``: the JSON-lines records written as results are made (``StageResult``);
- ``scene_stage``: the generated scene and its image tracks;
- ``gsplat_kernels``: gsplat's CUDA kernels built in the background;
- ``train_arguments``: the ``ns-train`` arguments of the check's runs;
- ``measured_train``: training runs in one process, measured as they go (step times, camera errors, a clean stop
  before the deadline, the evaluation);
- ``step_log``, ``camera_error_log``: the files those measurements are appended to;
- ``stock_nerfacto``: the camera interface S2CamP's evaluation needs, for a stock ``nerfacto`` run;
- ``timing``, ``tests_stage``, ``rest``: the stages;
- ``report``: the report, rebuilt from the folder;
- ``cli``: the stages in order (``python -m s2camp_bench.gpu_check``);
- ``regime``, ``regime_report``: the regime command (``python -m s2camp_bench.gpu_check.regime``);
- ``bundle``, ``wheels``, ``device_image``: the offline bundle of wheels a lent GPU machine needs
  (``python -m s2camp_bench.gpu_check.bundle``).
"""
