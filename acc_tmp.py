import warnings, time, numpy as np
from o3d_mvps import RefineOptions, refine, synthetic
from o3d_mvps.metrics import evaluate
cap = synthetic.render_capture("bunny", frames=20, size=(640, 480), scale_factor=4)
from o3d_mvps.odometry import initial_poses
for drop in (True,):
    t = time.time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = refine(cap, RefineOptions(progress=False, drop_depth_outliers=drop))
    print(drop, round(time.time() - t), evaluate(r, cap.groundtruth), r.info.get("reference_depth_outliers"), flush=True)
