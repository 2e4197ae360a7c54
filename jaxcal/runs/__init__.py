"""Run folders: their layout, checkpoints, metrics log, atomic writes and lock.

Host-only leaves at the bottom of the package (they know files, not models):

* :mod:`jaxcal.runs.folder`: what ``runs/<name>/`` holds, resume checks, JSON files;
* :mod:`jaxcal.runs.checkpoint`: Orbax checkpoints of whole pytrees + ``config.json``;
* :mod:`jaxcal.runs.metrics_log`: the JSON-lines metrics log;
* :mod:`jaxcal.runs.atomic`: the one atomic writer (temporary file, then rename);
* :mod:`jaxcal.runs.lock`: run names confined to the runs folder, one training of a
  run at a time.

Reading a trained *policy* back needs the training job's config and components:
that reader is the policy method's (:mod:`jaxcal.calibrators.methods.policy.loading`,
re-exported as :func:`jaxcal.deploy.load_run`).
"""
