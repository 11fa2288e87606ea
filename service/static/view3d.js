// Interactive view of the affine reconstruction (reconstruction.glb): scene 0 the final mesh,
// scene 1 the initial one, textured with the reference image. three.js is vendored.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";

export class View3D {
  constructor(container) {
    this.container = container;
    container.replaceChildren();
    container.dataset.ready = "";
    // preserveDrawingBuffer: the picture can be read back (screenshots, tests).
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.renderer.setClearColor(0x20262c);
    container.append(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(35, 1, 1, 1e7);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener("change", () => this.draw());
    this.resize = () => this.fit();
    this.observer = new ResizeObserver(this.resize);
    this.observer.observe(container);
    this.groups = [];
  }

  load(buffer) {
    return new Promise((resolve, reject) => {
      new GLTFLoader().parse(buffer, "", (gltf) => {
        this.groups = gltf.scenes;
        let triangles = 0;
        for (const group of this.groups) {
          group.traverse((node) => {
            if (node.isMesh) {
              node.material.side = THREE.DoubleSide;
              if (group === this.groups[0]) triangles += node.geometry.index.count / 3;
            }
          });
          this.scene.add(group);
        }
        this.showScene(0);
        this.frame();
        // Once more at the next frame: the first draw can precede the texture's upload.
        requestAnimationFrame(() => this.draw());
        this.container.dataset.triangles = String(triangles);
        this.container.dataset.ready = "1";
        resolve();
      }, reject);
    });
  }

  showScene(index) {
    this.groups.forEach((group, i) => { group.visible = i === index; });
    this.draw();
  }

  frame() {
    // Look at the reconstruction from the reference camera's side, slightly turned, so that
    // the relief shows at once.
    const box = new THREE.Box3().setFromObject(this.groups[0]);
    const centre = box.getCenter(new THREE.Vector3());
    const radius = box.getSize(new THREE.Vector3()).length() / 2 || 1;
    const distance = 0.8 * radius / Math.sin(THREE.MathUtils.degToRad(this.camera.fov / 2));
    const direction = new THREE.Vector3(0.35, -0.45, 1).normalize();
    this.camera.position.copy(centre).addScaledVector(direction, distance);
    this.camera.near = distance / 100;
    this.camera.far = distance * 100;
    this.controls.target.copy(centre);
    this.controls.update();
    this.fit();
  }

  fit() {
    const { clientWidth: w, clientHeight: h } = this.container;
    if (!w || !h) return;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.draw();
  }

  draw() {
    this.renderer.render(this.scene, this.camera);
  }

  dispose() {
    this.observer.disconnect();
    this.controls.dispose();
    this.renderer.dispose();
    this.container.replaceChildren();
  }
}
