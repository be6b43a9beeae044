// Shared drawing helpers for the auditor pages (plain JS, no build step).
"use strict";

// 256-entry palette: index 0 (touching) is bright yellow-white, 255 (horizon) is dark blue.
const NAVI_PALETTE = (() => {
  const stops = [[255, 255, 210], [255, 200, 40], [230, 80, 20], [140, 20, 90], [40, 20, 110], [5, 5, 30]];
  const table = new Uint8Array(256 * 3);
  for (let i = 0; i < 256; i++) {
    const x = (i / 255) * (stops.length - 1);
    const k = Math.min(Math.floor(x), stops.length - 2);
    const f = x - k;
    for (let c = 0; c < 3; c++) table[i * 3 + c] = Math.round(stops[k][c] * (1 - f) + stops[k + 1][c] * f);
  }
  return table;
})();

// Draw a base64 uint8 (height, width) row-major frame onto a canvas through the palette.
function naviDrawFrame(canvas, frame) {
  const raw = atob(frame.data);
  if (canvas.width !== frame.width || canvas.height !== frame.height) {
    canvas.width = frame.width;
    canvas.height = frame.height;
  }
  const ctx = canvas.getContext("2d");
  const image = ctx.createImageData(frame.width, frame.height);
  for (let i = 0; i < raw.length; i++) {
    const v = raw.charCodeAt(i);
    image.data[i * 4] = NAVI_PALETTE[v * 3];
    image.data[i * 4 + 1] = NAVI_PALETTE[v * 3 + 1];
    image.data[i * 4 + 2] = NAVI_PALETTE[v * 3 + 2];
    image.data[i * 4 + 3] = 255;
  }
  ctx.putImageData(image, 0, 0);
  canvas.dataset.seq = String(frame.seq);
}

// Line chart of {name: [[step, value], ...]} series.
function naviDrawChart(canvas, series) {
  const ctx = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height, pad = 28;
  ctx.clearRect(0, 0, w, h);
  const names = Object.keys(series || {});
  let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
  for (const name of names) for (const [x, y] of series[name]) {
    x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y);
  }
  ctx.fillStyle = "#889"; ctx.font = "11px monospace";
  if (!names.length || !isFinite(x0)) { ctx.fillText("no data yet", pad, h / 2); return; }
  if (x1 === x0) x1 = x0 + 1;
  if (y1 === y0) { y1 += 1; y0 -= 1; }
  ctx.fillText(y1.toPrecision(4), 2, 10); ctx.fillText(y0.toPrecision(4), 2, h - 4);
  const colors = ["#6cf", "#fc6", "#9f9", "#f99", "#c9f", "#ff9", "#9ff", "#fff"];
  names.forEach((name, i) => {
    ctx.strokeStyle = colors[i % colors.length]; ctx.beginPath();
    series[name].forEach(([x, y], j) => {
      const px = pad + ((x - x0) / (x1 - x0)) * (w - pad - 4);
      const py = h - 14 - ((y - y0) / (y1 - y0)) * (h - 24);
      if (j === 0) ctx.moveTo(px, py); else ctx.lineTo(px, py);
    });
    ctx.stroke();
    ctx.fillStyle = colors[i % colors.length];
    ctx.fillText(name, w - 6 - ctx.measureText(name).width, 12 + i * 12);
  });
}

// Open a WebSocket to `path` that reconnects forever; `onMessage` gets parsed JSON.
function naviConnect(path, onMessage, onLink) {
  const url = (location.protocol === "https:" ? "wss://" : "ws://") + location.host + path;
  let socket = null;
  const open = () => {
    socket = new WebSocket(url);
    socket.onopen = () => onLink(true);
    socket.onmessage = (ev) => onMessage(JSON.parse(ev.data));
    socket.onclose = () => { onLink(false); setTimeout(open, 1000); };
    socket.onerror = () => socket.close();
  };
  open();
  return { send: (obj) => { if (socket && socket.readyState === 1) socket.send(JSON.stringify(obj)); } };
}
