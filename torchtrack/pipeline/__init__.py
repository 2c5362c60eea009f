"""The per-frame pipeline (paper §III) and its policy stages, one module each:

- :mod:`~torchtrack.pipeline.tracker`: :class:`Tracker`, the pipeline composed of its stages (select -> track ->
  weight -> update -> re-select), ``step`` once per frame;
- :mod:`~torchtrack.pipeline.state`: :class:`TrackerState` (what it carries between frames) and :class:`StepResult`;
- :mod:`~torchtrack.pipeline.reselect`: when and how a new model is taken (``reselect`` config group);
- :mod:`~torchtrack.pipeline.outliers`: which features leave the model after the update (``outliers``);
- :mod:`~torchtrack.pipeline.keyframes`: the one keyframe store the landmarks and the relocaliser share
  (``keyframes``);
- :mod:`~torchtrack.pipeline.landmarks`: model points that outlive their model, re-acquired from keyframes
  (``landmarks``);
- :mod:`~torchtrack.pipeline.relocalise`: the loss check and relocalisation (``relocalise``).

The per-frame stages it is composed of besides (front end, region, selection, LK, weighting, back end, dense map)
live with their kind: :mod:`torchtrack.frontend`, :mod:`torchtrack.image`, :mod:`torchtrack.filter`,
:mod:`torchtrack.estimators`, :mod:`torchtrack.map`. Each stage is built by :func:`torchtrack.factory.build_tracker` from its own config
group; each takes plain keyword arguments whose defaults equal its schema's (:mod:`torchtrack.config`,
``tests/test_config.py``).
"""

from torchtrack.pipeline.state import StepResult, TrackerState
from torchtrack.pipeline.tracker import Tracker

__all__ = ["StepResult", "Tracker", "TrackerState"]
