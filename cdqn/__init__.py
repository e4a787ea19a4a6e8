"""cdqn: controlled deep Q-learning.

Deep Q-learning is modelled, through the neural tangent kernel (NTK) of a wide
two-layer ReLU network, as an uncertain linear system whose states are
``Q1 = Q(s, a)`` and ``Q2 = max_a' Q(s', a')`` (Varga, Kulcsár and Haghir Chehreghani,
"Deep Q-learning: a robust control approach", IJRNC 2022).  A feedback controller injects
a control reward ``u(t)`` into the temporal-difference loss so that learning converges
without a target network or random replay.
"""

__version__ = "0.1.0"
