"""msflow's version (its own module, so that records can name it without importing the package API)."""

__version__ = "0.1.0"
#: the version of what cache keys mean (msflow.runner.key_parts): bumped by any change that alters stored results;
#: here, in a leaf module, so workers can check a job's key scheme without importing the runner
KEY_SCHEME = 2  # 2: artifact format 2 (streamed array hashes, chunk checksums)


def package_version() -> str:
    """The installed distribution's version (what pip reports), else this module's: a source tree on PYTHONPATH
    that was never installed still has one."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("msflow")
    except PackageNotFoundError:
        return __version__
