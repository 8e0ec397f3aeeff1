"""The trainings the suite shares between its processes (a pytest plugin, registered by tests/conftest.py).

- The cache of models the node trains on start (node/scene/model_cache.py: ``SUPRAMODAL_CACHE``) is the
  run's own, in the run's shared folder (:mod:`harness.shared_folder`), never the user's: a node run in or
  out of a test's process reads the model another process of the run trained. Set before any test starts a
  process, which inherits it.
- The models the node trains on start that a test trains outside that cache (with a cache of its own, or
  none: ``build.texture_set_model``), and the fusions' trainings (:func:`_share_fusion_training`), are run
  once per run (:func:`harness.run_once.once_per_arguments`): seeded and deterministic, keyed by the
  content of their arguments.

Why: many tests, on every worker, ask for the same trainings (many scenes of the two-sense world build the
same fusion); each worker trained each again.

Relies on: pytest's ``pytest_sessionstart``; pytest-xdist registering its controller as the plugin
``dsession`` (to leave the controller, which runs no test, alone); :mod:`harness.shared_folder` and
:mod:`harness.run_once`; the names it replaces in supramodal (``node.scene.build.texture_set_model``,
``fused_model.senses_out_of_fold``, ``fused_model.EarlyFusionModel.train``), looked up by their callers
at each call.
"""

import os

from harness import shared_folder
from harness.run_once import once_per_arguments


def _share_fusion_training():
    """What the node trains to fuse two senses trained on the spot, once per run: the out-of-fold
    log-posteriors a learned late-fusion weight is fitted on (``senses_out_of_fold``: 2 x 10 networks,
    as node.build calls it, looked up in supramodal.fused_model at each build) and the early-fusion
    network (``EarlyFusionModel.train``), both seeded and deterministic. Many scenes of the two-sense
    world build the same fusion; each xdist worker trained it again for each."""
    from supramodal import fused_model

    fused_model.senses_out_of_fold = once_per_arguments(
        fused_model.senses_out_of_fold, "senses_out_of_fold", lambda kw: kw.get("progress") is None)
    train = fused_model.EarlyFusionModel.train.__func__
    fused_model.EarlyFusionModel.train = classmethod(once_per_arguments(
        train, "EarlyFusionModel.train", lambda kw: kw.get("calibration_progress") is None))


def pytest_sessionstart(session):
    """The run's model cache, in every process; the trainings shared, in every process that runs tests."""
    os.environ["SUPRAMODAL_CACHE"] = str(shared_folder.folder() / "model-cache")   # model_cache.CACHE_ENV
    if session.config.pluginmanager.hasplugin("dsession"):
        return                               # xdist's controller: it runs no test (and starts the workers sooner)
    from supramodal.node.scene import build

    build.texture_set_model = once_per_arguments(build.texture_set_model, "texture_set_model",
                                                 lambda kw: kw.get("progress") is None)
    _share_fusion_training()
