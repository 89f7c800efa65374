"""What the benchmarks ran on: ratios against a peer depend on the processor (HBVM / IAS15 on
the outer solar system over 1e6 days measured 0.52 on one x86_64 machine and 0.43 on another),
so every results file names it."""
import os
import platform


def cpu_model() -> str:
    """The processor's model name (Linux: /proc/cpuinfo), else what :mod:`platform` knows."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> str:
    """``"x86_64 AMD EPYC, 2 cores"``: architecture, processor model and core count."""
    model = cpu_model()
    arch = platform.machine()
    name = model if model.startswith(arch) else f"{arch} {model}".strip()
    return f"{name}, {os.cpu_count()} cores"
