"""The model files shipped with piezo-fmu (``paper.toml``: the paper's device and compensator).

``pyproject.toml`` maps this top-level folder into the wheel as ``piezo_fmu.model_files``; this
file makes it a regular package so that ``importlib.resources`` finds it in an editable install
too. Built FMUs that land here in a checkout are not part of the package.
"""
