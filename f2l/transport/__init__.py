"""Light transport from face pixels to lat-long probe texels: visibility rays and the operator T.

T[p, w] = V(p, w) max(0, <n_p, w>) dOmega_w / pi; shading = albedo * (T @ l).
"""

from f2l.transport.operator import Transport
from f2l.transport.visibility import compute_visibility, packed_width, unpack_bits, visibility_stats

__all__ = ["Transport", "compute_visibility", "visibility_stats", "packed_width", "unpack_bits"]
