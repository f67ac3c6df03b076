from s2camp_ns.gpu_check.cli import entrypoint

entrypoint()
