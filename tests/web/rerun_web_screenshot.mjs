// Opens a `ufops view` recording in rerun's own web viewer (served by `rerun --serve-web FILE.rrd`
// on loopback) in Debian's headless Chromium (playwright-core) and takes a screenshot, so that a
// person can see the cameras the recording carries. Started by
// scripts/rerun_web_screenshot.sh. The viewer draws on a WebGL/WebGPU canvas, so there is no DOM to
// query for the cameras: the script checks that the canvas is up and not blank, and the screenshot
// is what one looks at.
//
// usage: node rerun_web_screenshot.mjs VIEWER_URL OUT.png [WAIT_MS]
import { chromium } from 'playwright-core';

const [url, out, waitMs] = process.argv.slice(2);
if (!url || !out) {
  console.error('usage: node rerun_web_screenshot.mjs VIEWER_URL OUT.png [WAIT_MS]');
  process.exit(2);
}
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
  headless: true,
  // Software WebGL (SwiftShader): the machine has no GPU.
  args: ['--no-sandbox', '--disable-dev-shm-usage', '--use-gl=angle', '--use-angle=swiftshader', '--enable-unsafe-swiftshader'],
});
try {
  const page = await (await browser.newContext({ viewport: { width: 1600, height: 1000 } })).newPage();
  // The viewer also fetches from the internet (no network here): those errors are noise.
  page.on('console', (m) => {
    const t = m.text();
    if (m.type() === 'error' && !/ERR_NAME_NOT_RESOLVED|Failed to fetch/.test(t)) console.error('[viewer]', t);
  });
  await page.goto(url);
  await page.waitForSelector('canvas', { timeout: 60000 });
  await page.waitForTimeout(Number(waitMs || 20000));
  await page.screenshot({ path: out });
  const size = await page.evaluate(() => { const c = document.querySelector('canvas'); return [c.width, c.height]; });
  if (size[0] < 100 || size[1] < 100) throw new Error(`viewer canvas too small: ${size}`);
  console.log(JSON.stringify({ screenshot: out, canvas: size }));
} finally {
  await browser.close();
}
