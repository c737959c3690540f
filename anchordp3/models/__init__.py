"""Torch modules of AnchorDP3: segmenter, instruction classifier, task encoders, U-Net, diffusion policy.

Pure torch (plus ``diffusers`` for the DDIM scheduler and ``transformers`` for the classifier's
encoder); imports only ``anchordp3.schemas`` from this package. Submodules are imported on demand:
``from anchordp3.models.policy import AnchorDiffusionPolicy``.
"""
