"""boostnerf: a model-agnostic mixture of Fast-NeRF experts, as a staged command-line tool."""

__version__ = "0.1.0"
