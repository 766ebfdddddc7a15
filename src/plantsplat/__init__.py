"""plantsplat: object-centric 3D Gaussian Splatting of potted plants, with metric traits."""

__version__ = "0.1.0"
