"""Networks, losses, metrics and the model zoo of DELIFFAS and its variants."""

from deliffas.models.deliffas import VARIANTS, DeliffasModel, FrameFeatures, ModelConfig
from deliffas.models.encoding import PositionalEncoding, positional_encoding
from deliffas.models.light_field import LightFieldMLP, LightFieldMLPConfig
from deliffas.models.losses import PerceptualLoss, l1_foreground
from deliffas.models.metrics import Evaluator, perceptual_metrics_status, psnr, ssim
from deliffas.models.ray_query import RayQuery
from deliffas.models.unet import UNet, UNetConfig, optimize_for_inference
from deliffas.models.variants import VariantSpec, get_variant, register_variant, variant_names
from deliffas.models.vgg import BackboneRecord, PerceptualWeightsUnavailable, load_vgg16_weights
from deliffas.models.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from deliffas.models.zoo import get_config, list_models

__all__ = [
    "VARIANTS",
    "BackboneRecord",
    "CheckpointError",
    "DeliffasModel",
    "Evaluator",
    "FrameFeatures",
    "LightFieldMLP",
    "LightFieldMLPConfig",
    "ModelConfig",
    "PerceptualLoss",
    "PerceptualWeightsUnavailable",
    "PositionalEncoding",
    "RayQuery",
    "UNet",
    "UNetConfig",
    "VariantSpec",
    "get_config",
    "get_variant",
    "l1_foreground",
    "list_models",
    "load_checkpoint",
    "load_vgg16_weights",
    "optimize_for_inference",
    "perceptual_metrics_status",
    "positional_encoding",
    "psnr",
    "register_variant",
    "save_checkpoint",
    "ssim",
    "variant_names",
]
