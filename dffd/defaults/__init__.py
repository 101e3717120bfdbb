"""The service's packaged defaults: ``dffd.toml`` (the embedded default config) and ``lenses/``.

Data only; read them through :mod:`dffd.resources`.
"""
