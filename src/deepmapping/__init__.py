"""DeepMapping: unsupervised map estimation from multiple point clouds (Ding & Feng, CVPR 2019).

Heavy dependencies (torch, matplotlib) are imported where used, not here.
"""

__version__ = "0.1.0"

__all__ = ["register", "Result", "ScanSet", "Config", "__version__"]


def __getattr__(name):  # lazy API so `import deepmapping` stays cheap
    if name in ("register", "Result"):
        from deepmapping import api

        return getattr(api, name)
    if name == "ScanSet":
        from deepmapping.data import ScanSet

        return ScanSet
    if name == "Config":
        from deepmapping.config import Config

        return Config
    raise AttributeError(name)
