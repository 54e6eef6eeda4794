"""Make the pictures of docs/img from the README tour's outputs: run the tour's commands in a folder holding
a copy of the bundled example (`autoalign/data/example`), then `python make_images.py DOCS_IMG_DIR` there."""
import json, sys
from pathlib import Path
import cv2, numpy as np

dst = Path(sys.argv[1])
def save(img, name, width):
    h, w = img.shape[:2]
    if w > width:
        img = cv2.resize(img, (width, round(h * width / w)), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(dst / name), img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(name, img.shape, (dst / name).stat().st_size // 1000, "KB")

for src, name, width in [("out/example/overlay.png", "refine.png", 900),
                         ("out/example_models/overlay.png", "refine-models.png", 800),
                         ("out/capture_scene/trajectory.png", "recon.png", 800),
                         ("out/example_check/check.png", "check.png", 800),
                         ("out/example_compare/compare.png", "check-against.png", 1200)]:
    save(cv2.imread(src), name, width)

# export: photo, mask_visib tinted, bbox_visib, for four images side by side
info = json.loads(Path("out/example_bop/scene_gt_info.json").read_text())
tiles = []
for im in (0, 6, 12, 18):
    photo = cv2.imread(f"out/example_bop/rgb/{im:06d}.jpg")
    mask = cv2.imread(f"out/example_bop/mask_visib/{im:06d}_000000.png", cv2.IMREAD_GRAYSCALE) > 0
    photo[mask] = (0.5 * photo[mask] + 0.5 * np.array([255, 255, 0])).astype(np.uint8)
    x, y, w, h = info[str(im)][0]["bbox_visib"]
    cv2.rectangle(photo, (x, y), (x + w - 1, y + h - 1), (0, 0, 255), 2)
    cv2.putText(photo, f"image {im}: mask_visib, bbox_visib", (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    tiles.append(photo)
save(np.hstack(tiles), "export.png", 1200)
