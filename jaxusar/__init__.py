"""jaxusar: a JAX-vectorized trainer for multi-agent hierarchical RL in urban search and rescue.

Reproduces and extends Le, Hughes and Sycara, "Multi-agent Hierarchical Reinforcement Learning in
Urban and Search Rescue". See README.md.
"""

from jaxusar import envs, planning

__version__ = "0.1.0"
__all__ = ["envs", "planning", "__version__"]
