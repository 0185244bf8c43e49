"""
Refine a region (the lens)
==========================

Optimise the opacities for one rectangle of the image only (``region=("rect", x0, y0, x1,
y1)`` in pixels, y down; also ``("circle", cx, cy, r)`` or a boolean mask), as the web app's
lens and ``dvr-perception optimize --region X0,Y0,X1,Y1`` do, and compare the lens's terms with
the whole image's.
"""

import matplotlib.pyplot as plt
from matplotlib.patches import Rectangle

import dvr_perception as dp

volume, spec = dp.make_phantom(size=64)
camera = dp.Camera.from_view(
    volume.bounds, azimuth=30, elevation=20, zoom=1.6, width=128, height=128
)
x0, y0, x1, y1 = 32, 32, 96, 80
result = dp.optimize(
    volume, spec, camera, stages=("opacity",), region=("rect", x0, y0, x1, y1), seed=0
)
print(f"in the lens: E {result.initial['E']:.3f} -> {result.final['E']:.3f}")
print(f"whole image: E {result.initial['whole']['E']:.3f} -> {result.final['whole']['E']:.3f}")

# %%
after = dp.analyze(volume, result.spec, camera, occlusion_free=False, build_cache=False).image
fig, ax = plt.subplots(figsize=(4, 4))
ax.imshow(after)
ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="white"))
ax.set_title("after, lens in white")
ax.set_axis_off()
plt.show()
