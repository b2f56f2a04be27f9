"""Benchmarks that compare variants side by side in one run (`mat bench ...`).

Absolute times on shared machines are noisy; ratios measured in the same run are not.
"""

from __future__ import annotations

import platform


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    return f"{platform.node()} ({cpu}), python {platform.python_version()}"
