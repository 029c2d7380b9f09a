"""torchrl_softae: active exploration of soft-robot dynamics (SoftAE) as TorchRL components."""
__version__ = "0.1.0"
