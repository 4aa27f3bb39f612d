"""sdp: Sobolev Diffusion Policy toolkit (trajectory optimization + diffusion policies)."""

__version__ = "0.1.0"
