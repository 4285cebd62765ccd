"""The deprecation helper (:mod:`lfcore._deprecation`) for the application's own old names; here
so that the commands, which may not import lfcore, reach it too."""

from lfcore._deprecation import deprecated, deprecated_alias, keyword_options, moved_names

__all__ = ["deprecated", "deprecated_alias", "keyword_options", "moved_names"]
