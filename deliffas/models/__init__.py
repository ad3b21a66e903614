"""Networks, losses, metrics and the model zoo of DELIFFAS and its variants.

The names below are imported from their modules when first used, so that importing a light module of this
package (``deliffas.models.model_table``, read by the command line while it parses) imports no torch.
"""

from typing import TYPE_CHECKING

from deliffas.optional import lazy_exports

if TYPE_CHECKING:  # the names for type checkers and the API docs; at run time __getattr__ imports them
    from deliffas.models.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
    from deliffas.models.deliffas import DeliffasModel, FrameFeatures, ModelConfig, VARIANTS
    from deliffas.models.encoding import PositionalEncoding, positional_encoding
    from deliffas.models.light_field import LightFieldMLP, LightFieldMLPConfig
    from deliffas.models.losses import PerceptualLoss, l1_foreground
    from deliffas.models.metrics import Evaluator, perceptual_metrics_status, psnr, ssim
    from deliffas.models.ray_query import RayQuery
    from deliffas.models.unet import UNet, UNetConfig, optimize_for_inference
    from deliffas.models.variants import VariantSpec, get_variant, register_variant, variant_names
    from deliffas.models.vgg import BackboneRecord, PerceptualWeightsUnavailable, load_vgg16_weights
    from deliffas.models.zoo import get_config, list_models

_HOMES = {
    "BackboneRecord": "deliffas.models.vgg",
    "CheckpointError": "deliffas.models.checkpoint",
    "DeliffasModel": "deliffas.models.deliffas",
    "Evaluator": "deliffas.models.metrics",
    "FrameFeatures": "deliffas.models.deliffas",
    "LightFieldMLP": "deliffas.models.light_field",
    "LightFieldMLPConfig": "deliffas.models.light_field",
    "ModelConfig": "deliffas.models.deliffas",
    "PerceptualLoss": "deliffas.models.losses",
    "PerceptualWeightsUnavailable": "deliffas.models.vgg",
    "PositionalEncoding": "deliffas.models.encoding",
    "RayQuery": "deliffas.models.ray_query",
    "UNet": "deliffas.models.unet",
    "UNetConfig": "deliffas.models.unet",
    "VARIANTS": "deliffas.models.deliffas",
    "VariantSpec": "deliffas.models.variants",
    "get_config": "deliffas.models.zoo",
    "get_variant": "deliffas.models.variants",
    "l1_foreground": "deliffas.models.losses",
    "list_models": "deliffas.models.zoo",
    "load_checkpoint": "deliffas.models.checkpoint",
    "load_vgg16_weights": "deliffas.models.vgg",
    "optimize_for_inference": "deliffas.models.unet",
    "perceptual_metrics_status": "deliffas.models.metrics",
    "positional_encoding": "deliffas.models.encoding",
    "psnr": "deliffas.models.metrics",
    "register_variant": "deliffas.models.variants",
    "save_checkpoint": "deliffas.models.checkpoint",
    "ssim": "deliffas.models.metrics",
    "variant_names": "deliffas.models.variants",
}

__all__ = sorted(_HOMES)


__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
