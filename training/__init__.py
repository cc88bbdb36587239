if __name__ != "tactile_deploy.training":  # imported by its folder's name, e.g. from the repository root
    raise ImportError(f"the folder training/ is the package tactile_deploy.training: import it by that name "
                      f"(importing it as {__name__!r} would load a second copy of its modules)")
