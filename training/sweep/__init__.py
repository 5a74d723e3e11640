"""``pointtrack sweep``: seeds, grids and weather conditions as Ray Tune trials (docs/cluster.md).

- :mod:`training.sweep.spec`: the YAML spec, validated and expanded into trials before any runs;
- :mod:`training.sweep.runner`: the trials on Ray Tune, each the ordinary command in its own run
  directory, retried and resumed;
- :mod:`training.sweep.summary`: per-trial metrics and the mean +- sd table;
- :mod:`training.sweep.ray_backend`: connecting to Ray (optional extra ``sweep``) and the Ray
  task map behind ``pointtrack eval --weather ... --backend ray``.

Ray is imported only inside functions: without the extra, everything but running says so in
one line.
"""
