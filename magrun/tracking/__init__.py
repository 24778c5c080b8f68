"""Camera tracking and the fluoroscopy mimic (paper, Section II-F).

- :mod:`~magrun.tracking.camera`: the top-view camera model and its px ↔ m mapping;
- :mod:`~magrun.tracking.render`: synthetic frames of the workspace and the robots (OpenCV);
- :mod:`~magrun.tracking.keypoints`: the three fiducials and the pose they determine;
- :mod:`~magrun.tracking.unet`, :mod:`~magrun.tracking.tracker`: the keypoint UNet (torch)
  and the frame → pose tracker built on it, which runs the network's ONNX graph
  (:mod:`~magrun.tracking.inference`, :mod:`~magrun.tracking.weights`,
  :mod:`~magrun.tracking.heatmaps`; :mod:`~magrun.tracking.export` writes the graph);
- :mod:`~magrun.tracking.dataset`, :mod:`~magrun.tracking.train`,
  :mod:`~magrun.tracking.evaluate`: training data (rendered, or a lab's annotated frames),
  training and held-out evaluation (``magrun tracker train|eval``);
- :mod:`~magrun.tracking.fluoroscopy`: degrading the camera pose stream to fluoroscopy's
  rate and noise.

Only ``unet``, ``train`` and ``export`` import torch, the ``train`` extra: running, tracking
and evaluating a tracker need none (an import-linter contract and a test without torch
check it).
"""
