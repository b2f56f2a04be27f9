"""MAT SDK: train Multi-Agent Transformer policies on multi-agent MuJoCo robots."""

__version__ = "0.1.0"
