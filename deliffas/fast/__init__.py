"""The real-time path on CPU: rasterised uvs, per-ray inputs fused into the MLP, C kernels compiled at first use.

Reading order for a newcomer:

* :mod:`deliffas.fast.config`: :class:`~deliffas.fast.config.RenderPathConfig`, the render path (fast or plain),
  the uv source and every switch of the fast path (the config ``eval``, ``render`` and ``view`` nest);
* :mod:`deliffas.fast.rasterize`: :class:`~deliffas.fast.rasterize.UVRasterizer`, each pixel's inner/outer uvs
  with depth peeling (the ray caster's hits), C kernel ``csrc/rasterize.c``, numpy fallback;
* :mod:`deliffas.fast.uv_sources`: the three uv sources side by side (the C rasteriser, the ray caster, the torch
  rasteriser) and ``auto`` resolved, for both paths and for training;
* :mod:`deliffas.fast.shade`: :class:`~deliffas.fast.shade.FastShader`, ``DeliffasModel.shade`` for inference
  (``csrc/ray_inputs.c``: sampled features and encodings as GEMM operands; ``csrc/fused_shade.c``: the whole
  MLP in one pass, its tile inputs in ``csrc/fused_tiles.h``), the torch path as fallback;
* :mod:`deliffas.fast.frame`: a camera's image from them (``fast_render_camera``: uv, sample and mlp stages on
  any timer with ``stage(name)``), the ray caster where a vertex is behind the camera, and ``render_stream``
  (several frames in flight). The rays and their way to the model are the engine's too
  (``geometry.camera_rays``, ``models.ray_query``); the engine picks the path (``path_for_device``).

The U-Net's CPU kernels (``models/unet_cpu.py``, ``unet_prepack.py``, ``unet_conv.py``) stay in ``models``: they
are the U-Net's own layers (``unet_conv.Conv2d`` and ``ConvTranspose2d`` are what ``models.unet`` is built of,
for training and inference alike), and ``models`` may not import ``fast``. The normal-map gather stays in
``geometry`` (conversion uses it). All C sources sit in ``deliffas/csrc/`` and are compiled by
:mod:`deliffas.native`.
"""
