"""mmsclean: cleaning mobile-mapping point clouds for HD road maps."""

__version__ = "0.1.0"
