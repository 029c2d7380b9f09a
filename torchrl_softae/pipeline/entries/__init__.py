"""Per-family pipeline entries (coverage projection, held-out set, config defaults), one module per
``EnvRecord.family``; :func:`torchrl_softae.pipeline.catalog.get_env_entry` builds them."""
