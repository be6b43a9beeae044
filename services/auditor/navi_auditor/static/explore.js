// The explorer: sends the held keys to the server (which flies the drone) and draws the view it pushes.
"use strict";

const $ = (id) => document.getElementById(id);
const FLIGHT_KEYS = new Set(["w", "a", "s", "d", "q", "e", " ", "shift"]);
const held = new Set();

function keyName(ev) {
  return ev.key === "Shift" ? "shift" : ev.key.toLowerCase();
}

function render(msg) {
  $("saved").textContent = "Saved " + msg.saved.length;
  $("held").textContent = msg.keys.length ? msg.keys.map((k) => (k === " " ? "space" : k)).join(" ") : "none";
  $("waiting").className = msg.finished ? "overlay" : "overlay hidden";
  if (msg.scene === undefined) return;
  $("scene").textContent = "Scene " + (msg.scene_index + 1) + "/" + msg.scenes + " " + msg.scene;
  $("step").textContent = "Step " + msg.step + "/" + msg.max_steps;
  $("reward").textContent = "Reward " + msg.reward.toFixed(3) + " (episode " + msg.episode_return.toFixed(2) + ")";
  $("pose").textContent = "Pose " + msg.position.join(", ") + " yaw " + msg.yaw;
  naviDrawFrame($("heatmap"), msg.frame);
  const obstacles = msg.obstacles;
  $("obstacles").textContent = obstacles === undefined ? "" :
    "Obstacles " + obstacles.active + (obstacles.nearest === null ? "" : ", nearest " + obstacles.nearest + " m") +
    ", hit " + obstacles.collisions;
  if (obstacles !== undefined) tintObstacles($("heatmap"), obstacles.mask);
}

// Tint the pixels that see a moving obstacle (mask: base64 uint8, 1 = obstacle) green.
function tintObstacles(canvas, mask) {
  const raw = atob(mask);
  const ctx = canvas.getContext("2d");
  const image = ctx.getImageData(0, 0, canvas.width, canvas.height);
  for (let i = 0; i < raw.length; i++) {
    if (raw.charCodeAt(i) === 0) continue;
    image.data[i * 4] = image.data[i * 4] >> 2;
    image.data[i * 4 + 1] = 255;
    image.data[i * 4 + 2] = image.data[i * 4 + 2] >> 1;
  }
  ctx.putImageData(image, 0, 0);
}

const link = naviConnect("/ws/explore", render, (up) => {
  $("link").textContent = up ? "live" : "disconnected";
  $("link").className = up ? "up" : "down";
});

function sendKeys() {
  link.send({ type: "keys", pressed: Array.from(held) });
}

document.addEventListener("keydown", (ev) => {
  const key = keyName(ev);
  if (key === "escape") { link.send({ type: "next" }); ev.preventDefault(); return; }
  if (!FLIGHT_KEYS.has(key)) return;
  ev.preventDefault();
  if (!held.has(key)) { held.add(key); sendKeys(); }
});
document.addEventListener("keyup", (ev) => {
  const key = keyName(ev);
  if (held.delete(key)) sendKeys();
});
window.addEventListener("blur", () => { held.clear(); sendKeys(); });
