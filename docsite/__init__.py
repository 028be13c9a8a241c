"""The manual's generated pages: what the code itself says, made when the site is built.

``mkdocs.yml`` loads :mod:`docsite.hooks`, which adds these pages to the site as it is built
(``scripts/docs``); none of them is a file in the repository, so none can drift from the
code or be forgotten at a change:

- the configuration reference, from the config's own models (:mod:`docsite.config_reference`);
- the command reference, from the commands' own help (:mod:`docsite.cli_reference`);
- the metric reference, from a running demo's ``/metrics`` (:mod:`docsite.metrics_reference`);
- one page per sensor family with its profiles' register maps (:mod:`docsite.sensors`);
- copies of ``deploy/README.md`` and ``bench/README.md``, which stay beside the files they
  describe (:mod:`docsite.copies`).

Generated rather than committed: a committed copy needs a test that fails whenever someone
adds a config key or a metric and forgets to regenerate, and a generated page cannot be
stale. ``tests/docs/`` checks that the pages cover every key and every metric family, and
that the site builds with ``--strict``.
"""
