"""splatcli: photographs to 3D Gaussian splats."""

__version__ = "0.1.0"


def __getattr__(name: str):
    # Lazy: `import splatcli` stays cheap for the CLI's --help and --version.
    if name in ("rasterize", "RenderOutput"):
        from . import render

        return getattr(render, name)
    if name == "Gaussians":
        from .gaussians import Gaussians

        return Gaussians
    raise AttributeError(name)


__all__ = ["rasterize", "RenderOutput", "Gaussians", "__version__"]
