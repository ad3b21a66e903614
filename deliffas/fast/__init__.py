"""The real-time path on CPU: rasterised uvs, per-ray inputs fused into the MLP, C kernels compiled at first use.

Reading order for a newcomer:

* :mod:`deliffas.fast.config`: :class:`~deliffas.fast.config.FastConfig`, every switch of the path;
* :mod:`deliffas.fast.rasterize`: :class:`~deliffas.fast.rasterize.UVRasterizer`, each pixel's inner/outer uvs
  with depth peeling (the ray caster's hits), C kernel ``csrc/rasterize.c``, numpy fallback;
* :mod:`deliffas.fast.shade`: :class:`~deliffas.fast.shade.FastShader`, ``DeliffasModel.shade`` for inference
  (``csrc/ray_inputs.c``: sampled features and encodings as GEMM operands; ``csrc/fused_shade.c``: the whole
  MLP in one pass), the torch path as fallback;
* ``deliffas.engine.realtime`` joins them to the engine's rays and timers (``fast_render_camera``,
  ``render_stream``).

The U-Net's inference kernels (``models/unet_cpu.py``, ``unet_prepack.py``, ``unet_conv.py``) stay in ``models``
(training runs the same U-Net modules), and the normal-map gather in ``geometry`` (conversion uses it); all C
sources sit in ``deliffas/csrc/`` and are compiled by :mod:`deliffas.native`.
"""
