// Top-down view of actor 0: the floor plan of its scene (grey = free, brighter = more clearance,
// black = inside geometry) with its trail (cyan) and its current position (red). +x right, +y up.
"use strict";

const NAVI_TRAIL_COLOR = [0, 220, 255];
const NAVI_POSE_COLOR = [255, 40, 40];

// World (x, y) meters -> canvas pixel, for the plan's extent (or the trail's when there is no plan).
function naviTrailFrame(canvas, plan, trail) {
  let x0, y0, size;
  if (plan) {
    x0 = plan.origin_x; y0 = plan.origin_y;
    size = Math.max(plan.width, plan.height) * plan.cell_size;
  } else {
    const xs = trail.map((p) => p[0]), ys = trail.map((p) => p[1]);
    x0 = Math.min(...xs) - 1; y0 = Math.min(...ys) - 1;
    size = Math.max(Math.max(...xs) - x0, Math.max(...ys) - y0) + 1;
  }
  const scale = canvas.width / size;
  return (x, y) => [(x - x0) * scale, canvas.height - (y - y0) * scale];
}

function naviDrawPlan(ctx, canvas, plan) {
  const raw = atob(plan.data);
  const image = ctx.createImageData(plan.width, plan.height);
  for (let row = 0; row < plan.height; row++) {
    for (let col = 0; col < plan.width; col++) {
      const v = raw.charCodeAt(row * plan.width + col);
      const at = ((plan.height - 1 - row) * plan.width + col) * 4;  // row 0 (smallest y) at the bottom
      image.data[at] = v; image.data[at + 1] = v; image.data[at + 2] = v; image.data[at + 3] = 255;
    }
  }
  const side = Math.max(plan.width, plan.height);
  const scratch = document.createElement("canvas");
  scratch.width = plan.width; scratch.height = plan.height;
  scratch.getContext("2d").putImageData(image, 0, 0);
  const px = canvas.width / side;
  ctx.imageSmoothingEnabled = false;
  ctx.drawImage(scratch, 0, canvas.height - plan.height * px, plan.width * px, plan.height * px);
}

function naviDrawTrail(canvas, plan, trail, pose) {
  const ctx = canvas.getContext("2d");
  ctx.fillStyle = "#181b21";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  const points = trail || [];
  if (plan) naviDrawPlan(ctx, canvas, plan);
  canvas.dataset.plan = plan ? String(plan.seq) : "0";
  if (!points.length) return;
  const toPixel = naviTrailFrame(canvas, plan, points);
  ctx.strokeStyle = "rgb(" + NAVI_TRAIL_COLOR.join(",") + ")";
  ctx.lineWidth = 2;
  ctx.beginPath();
  points.forEach(([x, y], i) => {
    const [px, py] = toPixel(x, y);
    if (i === 0) ctx.moveTo(px, py); else ctx.lineTo(px, py);
  });
  ctx.stroke();
  if (pose) {
    const [px, py] = toPixel(pose.x, pose.y);
    ctx.fillStyle = "rgb(" + NAVI_POSE_COLOR.join(",") + ")";
    ctx.beginPath(); ctx.arc(px, py, 4, 0, 2 * Math.PI); ctx.fill();
  }
  canvas.dataset.points = String(points.length);
}
