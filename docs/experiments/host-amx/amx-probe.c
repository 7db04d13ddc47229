#include <stdio.h>
#include <stdint.h>
#include <string.h>
#include <unistd.h>
#include <sys/syscall.h>
#include <immintrin.h>
#define ARCH_REQ_XCOMP_PERM 0x1023
#define XFEATURE_XTILEDATA 18
typedef struct { uint8_t palette, start; uint8_t r[14]; uint16_t colsb[16]; uint8_t rows[16]; } cfg_t;
int main(){
  long r = syscall(SYS_arch_prctl, ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA);
  printf("perm %ld\n", r);
  cfg_t c; memset(&c,0,sizeof c); c.palette=1;
  for(int i=0;i<3;i++){c.colsb[i]=64;c.rows[i]=16;}
  _tile_loadconfig(&c);
  static int8_t a[16*64], b[16*64]; static int32_t cc[16*16];
  for(int i=0;i<1024;i++){a[i]=(int8_t)(i*7+3); b[i]=(int8_t)(i*13-5);}
  _tile_zero(0); _tile_loadd(1,a,64); _tile_loadd(2,b,64); _tile_dpbssd(0,1,2); _tile_stored(0,cc,64);
  _tile_release();
  // reference
  int ok=1; for(int m=0;m<16;m++)for(int n=0;n<16;n++){int s=0; for(int k=0;k<64;k++) s+=a[m*64+k]*b[(k/4)*64+n*4+k%4]; if(s!=cc[m*16+n]) ok=0;}
  printf("ok %d %d\n", ok, cc[0]);
  // timing
  _tile_loadconfig(&c);
  _tile_loadd(1,a,64); _tile_loadd(2,b,64);
  uint64_t t0=__rdtsc(); for(int i=0;i<1000000;i++){ _tile_dpbssd(0,1,2);} uint64_t t1=__rdtsc();
  _tile_stored(0,cc,64); _tile_release();
  printf("cycles per tdpbssd %.2f  MAC/cycle %.0f\n",(t1-t0)/1e6, 16384.0/((t1-t0)/1e6));
}
