// Screenshot of the labeling page for one policy (the first episode), e.g. a generated ALOHA
// dataset's 3-camera grid. Started by scripts/rerun_web_screenshot.sh.
// Env: UFOPS_URL, UFOPS_TOKEN (a labeler), UFOPS_POLICY, OUT_PNG, CHROMIUM. Prints the cameras shown.
import { chromium } from 'playwright-core';

const { UFOPS_URL: URL, UFOPS_TOKEN: TOKEN, UFOPS_POLICY: POLICY, OUT_PNG: OUT } = process.env;
if (!URL || !TOKEN || !POLICY || !OUT) {
  console.error('set UFOPS_URL, UFOPS_TOKEN, UFOPS_POLICY and OUT_PNG');
  process.exit(2);
}
const browser = await chromium.launch({ executablePath: process.env.CHROMIUM || '/usr/bin/chromium', headless: true, args: ['--no-sandbox', '--disable-dev-shm-usage'] });
try {
  const page = await (await browser.newContext({ viewport: { width: 1440, height: 1000 } })).newPage();
  await page.goto(`${URL}/ui/#policy=${POLICY}`);
  await page.fill('#token', TOKEN);
  await page.keyboard.press('Enter');
  await page.waitForSelector('#app:not([hidden])');
  await page.waitForFunction(() => document.body.dataset.ready, null, { timeout: 30000 });
  await page.keyboard.press('ArrowRight');
  await page.waitForTimeout(3000);
  await page.screenshot({ path: OUT, fullPage: true });
  const cams = await page.evaluate(() => [...document.querySelectorAll('#videos img, #videos video, #videos canvas')].map((e) => e.dataset.key || e.alt || e.tagName));
  console.log(JSON.stringify({ screenshot: OUT, cameras: cams }));
} finally {
  await browser.close();
}
