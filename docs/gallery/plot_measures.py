"""
Render the phantom and measure it
=================================

Analyse the built-in phantom from one view and show the rendering beside the per-pixel
deviation maps of the three measures (visibility, shape, transparency; lower is better).
The same as ``dvr-perception measure phantom --size 128 --out-dir measures``.
"""

import matplotlib.pyplot as plt

import dvr_perception as dp

volume, spec = dp.make_phantom(size=64)
camera = dp.Camera.from_view(
    volume.bounds, azimuth=30, elevation=20, zoom=1.6, width=128, height=128
)
analysis = dp.analyze(volume, spec, camera)
measures = dp.all_measures(analysis, spec)

# %%
# The three terms and each structure's share of the picture against its target share:
v = measures.visibility
print(f"E_v {v.E_v:.3f}  E_s {measures.shape.E_s:.3f}  E_t {measures.transparency.E_t:.3f}")
for name, record in v.per_structure.items():
    share, target = record["visible_share"], record["target_share"]
    print(f"{name:14s} {share:6.1%} of the picture, target {target:6.1%}")

# %%
# The rendering and the deviation maps:
fig, axes = plt.subplots(1, 4, figsize=(12, 3.4))
axes[0].imshow(analysis.image)
axes[0].set_title("rendering")
for ax, (title, result) in zip(
    axes[1:],
    [
        ("visibility", measures.visibility),
        ("shape", measures.shape),
        ("transparency", measures.transparency),
    ],
    strict=True,
):
    im = ax.imshow(result.deviation, cmap="viridis", vmin=0)
    ax.set_title(f"{title} deviation")
    fig.colorbar(im, ax=ax, fraction=0.046)
for ax in axes:
    ax.set_axis_off()
fig.tight_layout()
plt.show()
