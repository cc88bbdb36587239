"""The discrepancy workflow: find where simulation and measurement disagree, name the missing
effect, add it to the sensor model, and show the gap shrink.

``find_discrepancy(sensor, measured)`` (:mod:`tactile_deploy.calibration.discrepancy.workflow`) runs it top to
bottom; one module per concept:

==================  ======================================================================
measured            matched data: depth maps or frames with their contacts (.npz / folder)
reproduce           contacts reproduced by the sensor model and its variants; estimation
candidates          the library of candidate effects (10) and how each is fitted
view_warp           optics effects seen in depth maps made through the calibrated camera
tables              each candidate's tabulated changes of each contact's map
noise               pixel noise of the maps
fingerprint         summaries of the residual that separate effects
selection           fits, held-out gains by contact, BIC, effect-free null, bootstrap
experiment          the probe contact that tells look-alikes apart
verdict             the JSON verdict and its text
apply               the effect written into a versioned sensor model
report              report.md, verdict.json and figures
synthetic           measured data with hidden effects from virtual sensors
cli                 ``tactile-deploy discrepancy``
==================  ======================================================================
"""
