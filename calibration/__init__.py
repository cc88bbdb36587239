if __name__ != "tactile_deploy.calibration":  # imported by its folder's name, e.g. from the repository root
    raise ImportError(f"the folder calibration/ is the package tactile_deploy.calibration: import it by that name "
                      f"(importing it as {__name__!r} would load a second copy of its modules)")
