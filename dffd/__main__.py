"""``python -m dffd`` is the same as the ``dffd`` command."""

from dffd.cli import entry_point

entry_point()
