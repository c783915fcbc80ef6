"""The built-in retargeters, one subpackage each, registered through entry points."""
