"""
Refine a region (the lens)
==========================

Optimise the opacities for one rectangle of the image only (``region``: pixels ``x0, y0, x1,
y1``, y down), as the web app's lens and ``dvr-perception optimize --region`` do, and compare
the whole image's and the lens's terms.
"""

import matplotlib.pyplot as plt
from matplotlib.patches import Rectangle

import dvr_perception as dp

volume, spec = dp.make_phantom(size=64)
camera = dp.Camera.from_view(volume.bounds, azimuth=30, elevation=20, width=128, height=128)
region = (32, 32, 96, 80)
result = dp.optimize(volume, spec, camera, stages=("opacity",), region=region, seed=0)
print(f"in the lens: E {result.initial['E']:.3f} -> {result.final['E']:.3f}")
print(f"whole image: E {result.initial['whole']['E']:.3f} -> {result.final['whole']['E']:.3f}")

# %%
after = dp.analyze(volume, result.spec, camera, occlusion_free=False).image
fig, ax = plt.subplots(figsize=(4, 4))
ax.imshow(after)
x0, y0, x1, y1 = region
ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="white"))
ax.set_title("after, lens in white")
ax.set_axis_off()
plt.show()
