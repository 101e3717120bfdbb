"""dffd — depth-from-focus daemon."""

__version__ = "0.1.0"
